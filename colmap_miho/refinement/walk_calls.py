"""The refine calls of the track walk: one per image pair and side, or one per level.

:mod:`.tracks` decides which keypoints move against which; this module turns a level's
groups (matches of one pair whose keypoints on one side move) into calls of the pairwise
refiner and writes the results back. On CUDA a call costs about the same for 100 matches as
for 10000, so all groups of a level go into one call on stacked images
(:class:`~.warping.ImageStack`), at most ``max_images`` images a call.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from .config import NCCConfig


@dataclass(frozen=True)
class Group:
    """Matches ``rows`` of ``pair`` whose side-``side`` keypoints (``free``) move at this
    level, each against the fixed keypoint ``anchor_of``; ``homs`` the pair's per-match
    homography pairs."""

    pair: tuple
    side: int
    rows: np.ndarray
    free: np.ndarray
    anchor_of: np.ndarray
    homs: np.ndarray


@dataclass(frozen=True)
class WalkState:
    """What the refine calls of the walk read and update (arrays are updated in place)."""

    pair_matches: Mapping
    pos: dict
    affines: Mapping | None
    cache: object  # tracks._ImageCache: .get(image_id) -> image or None
    ncc_cfg: NCCConfig
    refine_fn: Callable
    node_image: np.ndarray
    node_kp: np.ndarray
    out_disp: dict
    out_against: dict
    stats: dict


@dataclass(frozen=True)
class _Call:
    """One group oriented as (fixed, moving): keypoint indices, positions, homography pairs
    (fixed side first) and affine frames (or None)."""

    fixed_id: object
    moving_id: object
    moving_idx: np.ndarray
    pts_f: np.ndarray
    pts_m: np.ndarray
    homs: np.ndarray
    aff_f: np.ndarray | None
    aff_m: np.ndarray | None


def _orient(grp: Group, ctx: WalkState) -> _Call:
    id1, id2 = grp.pair
    m = np.asarray(ctx.pair_matches[grp.pair]).astype(np.int64).reshape(-1, 2)[grp.rows]
    homs = grp.homs[grp.rows]
    aff1 = aff2 = None
    if ctx.affines is not None and id1 in ctx.affines and id2 in ctx.affines:
        aff1 = np.asarray(ctx.affines[id1])[m[:, 0]]
        aff2 = np.asarray(ctx.affines[id2])[m[:, 1]]
    if grp.side == 2:
        return _Call(id1, id2, m[:, 1], ctx.pos[id1][m[:, 0]], ctx.pos[id2][m[:, 1]], homs,
                     aff1, aff2)
    return _Call(id2, id1, m[:, 0], ctx.pos[id2][m[:, 1]], ctx.pos[id1][m[:, 0]],
                 homs[:, ::-1], aff2, aff1)


def _apply(grp: Group, moving_id, idx, new, moved, displacement, rejected, ctx: WalkState):
    """Write one group's refinement result: keypoints ``idx`` of image ``moving_id`` were
    refined, ``moved`` says which of them moved to ``new``."""
    st = ctx.stats
    st["refined"] += int(grp.rows.size)
    ctx.pos[moving_id][idx[moved]] = new[moved]
    ctx.out_disp[moving_id][idx[moved]] = displacement[moved]
    ctx.out_against[moving_id][idx, 0] = ctx.node_image[grp.anchor_of]
    ctx.out_against[moving_id][idx, 1] = ctx.node_kp[grp.anchor_of]
    st["moved"] += int(moved.sum())
    st["rejected"] += int(np.asarray(rejected).sum())


def chunks_by_images(groups: list, max_images: int):
    """Consecutive runs of groups that together use at most ``max_images`` images."""
    chunk, ids = [], set()
    for grp in groups:
        both = ids | set(grp.pair)
        if chunk and len(both) > max_images:
            yield chunk
            chunk, both = [], set(grp.pair)
        chunk.append(grp)
        ids = both
    if chunk:
        yield chunk


def refine_batch(groups: list, ctx: WalkState, device) -> None:
    """Refine several groups in one call of the pairwise refiner, on stacked images."""
    from .warping import ImageStack, to_gray_tensor

    calls, kept = [], []
    for grp in groups:
        if ctx.cache.get(grp.pair[0]) is None or ctx.cache.get(grp.pair[1]) is None:
            ctx.stats["skipped"] += int(grp.rows.size)
            continue
        calls.append(_orient(grp, ctx))
        kept.append(grp)
    if not calls:
        return
    ids = list(dict.fromkeys(i for c in calls for i in (c.fixed_id, c.moving_id)))
    slot = {i: k for k, i in enumerate(ids)}
    sizes = [c.pts_f.shape[0] for c in calls]
    idx_f = np.repeat([slot[c.fixed_id] for c in calls], sizes)
    idx_m = np.repeat([slot[c.moving_id] for c in calls], sizes)
    stack_f = ImageStack.build([to_gray_tensor(ctx.cache.get(i), device) for i in ids], idx_f,
                               device)
    stack_m = stack_f.with_index(idx_m)
    aff = {}
    if any(c.aff_f is not None for c in calls):
        eye = np.eye(2)
        aff = {
            "affine1": np.concatenate([c.aff_f if c.aff_f is not None
                                       else np.tile(eye, (len(c.pts_f), 1, 1)) for c in calls]),
            "affine2": np.concatenate([c.aff_m if c.aff_m is not None
                                       else np.tile(eye, (len(c.pts_m), 1, 1)) for c in calls]),
        }
    res = ctx.refine_fn(stack_f, stack_m, np.concatenate([c.pts_f for c in calls]),
                        np.concatenate([c.pts_m for c in calls]),
                        np.concatenate([c.homs for c in calls]), move="2", config=ctx.ncc_cfg,
                        **aff)
    ctx.stats["refine_calls"] += 1
    start = 0
    for grp, call, n in zip(kept, calls, sizes):
        seg = slice(start, start + n)
        start += n
        _apply(grp, call.moving_id, call.moving_idx, res.pts2[seg],
               np.asarray(res.moved_side[seg]) == 2,
               np.asarray(res.displacement[seg]), res.rejected[seg], ctx)


def refine_group(grp: Group, ctx: WalkState) -> None:
    """One refine call: the matches of one group, on the pair's two images."""
    id1, id2 = grp.pair
    img1, img2 = ctx.cache.get(id1), ctx.cache.get(id2)
    if img1 is None or img2 is None:
        ctx.stats["skipped"] += int(grp.rows.size)
        return
    m = np.asarray(ctx.pair_matches[grp.pair]).astype(np.int64).reshape(-1, 2)[grp.rows]
    kwargs = {}
    if ctx.affines is not None and id1 in ctx.affines and id2 in ctx.affines:
        kwargs = {"affine1": np.asarray(ctx.affines[id1])[m[:, 0]],
                  "affine2": np.asarray(ctx.affines[id2])[m[:, 1]]}
    res = ctx.refine_fn(img1, img2, ctx.pos[id1][m[:, 0]], ctx.pos[id2][m[:, 1]],
                        grp.homs[grp.rows], move=str(grp.side), config=ctx.ncc_cfg, **kwargs)
    ctx.stats["refine_calls"] += 1
    new = res.pts2 if grp.side == 2 else res.pts1
    moving_id, idx = (id2, m[:, 1]) if grp.side == 2 else (id1, m[:, 0])
    _apply(grp, moving_id, idx, new, np.asarray(res.moved_side) == grp.side,
           np.asarray(res.displacement), res.rejected, ctx)
