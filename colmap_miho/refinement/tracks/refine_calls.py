"""The refine calls of the track walk: a level's groups become calls of the pairwise refiner, whose
results are written back. On CUDA a whole level goes into one call on stacked images (a call costs
little more for many matches than for few)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ...enums import Rectification
from ..config import NCCConfig
from ..lsm.step import LSM_COUNTERS
from .plan import TrackPlan

if TYPE_CHECKING:
    import torch

#: images by id: a Mapping (``.get``) or a callable; None (or absent) means missing.
Images = Mapping[int, np.ndarray | None] | Callable[[int], np.ndarray | None]


@dataclass(frozen=True)
class Group:
    """Edges of ``pair`` whose side-``side`` keypoints move at this level, each against ``partner``."""

    pair: tuple
    side: int
    edges: np.ndarray
    free: np.ndarray
    partner: np.ndarray

    @property
    def size(self) -> int:
        return int(self.edges.size)


class ImageSource:
    """Images by id from a Mapping or a callable (None: missing); no cache of its own."""

    def __init__(self, images: Images) -> None:
        self._load: Callable[[int], np.ndarray | None]
        if isinstance(images, Mapping):
            self._load = images.get
        elif callable(images):
            self._load = images
        else:
            raise ValueError("images must be a Mapping or a callable image_id -> array or None")
        self.missing: set = set()
        self.used: set = set()

    def get(self, image_id: int) -> np.ndarray | None:
        if image_id in self.missing:
            return None
        img = self._load(image_id)
        if img is None:
            self.missing.add(image_id)
        else:
            self.used.add(image_id)
        return img


@dataclass(frozen=True)
class WalkState:
    """What the refine calls of the walk read and update (arrays are updated in place).

    ``pos`` image_id -> (Ni, 2) current positions; ``score`` (T,) quality of each fixed
    node as a partner (NCC after refinement, +inf for anchors); ``moved`` (T,) bool;
    ``out_disp`` / ``out_against`` the result arrays of :class:`~.walk.TrackRefineResult`;
    ``gray`` the float32 tensors of the images of the last batched call (image_id ->
    tensor), reused by the next call instead of converting the same images again;
    ``far_move_px`` the far-move bound (pixels, ``rectify.max_residual_px``; None: off).
    """

    plan: TrackPlan
    pos: dict
    affines: Mapping | None
    images: ImageSource
    ncc_cfg: NCCConfig
    refine_fn: Callable
    score: np.ndarray
    moved: np.ndarray
    out_disp: dict
    out_against: dict
    stats: dict
    gray: dict = field(default_factory=dict)
    #: (T, 3, 3) float64 map from the anchor image's pixels to each fixed node's image
    #: pixels (identity at the anchors), or None where the joint pass (``multiphoto_lsm``)
    #: does not read it
    to_ref: np.ndarray | None = None
    far_move_px: float | None = None


@dataclass(frozen=True)
class _Call:
    """One group oriented as (fixed, moving): indices, positions, homography pairs and affine frames."""

    fixed_id: int
    moving_id: int
    fixed_idx: np.ndarray
    moving_idx: np.ndarray
    pts_f: np.ndarray
    pts_m: np.ndarray
    homs: np.ndarray
    aff_f: np.ndarray | None
    aff_m: np.ndarray | None


def _pairs_of(plan: TrackPlan, edges: np.ndarray, rectification: Rectification) -> np.ndarray:
    """Patch homography pairs of one pair's edges: "filter", "local", or both as candidates."""
    p = int(plan.edge_pair[edges[0]])
    filt = plan.pair_homs[p][plan.edge_label[edges]]
    pair_local = None if rectification is Rectification.FILTER else plan.local_pairs(p)
    if pair_local is None:
        return filt
    local = pair_local[plan.edge_row[edges]]
    return local if rectification is Rectification.LOCAL else np.stack([filt, local], axis=1)


def _orient(grp: Group, ctx: WalkState) -> _Call:
    plan = ctx.plan
    id1, id2 = grp.pair
    k1 = plan.node_kp[plan.edge_a[grp.edges]]
    k2 = plan.node_kp[plan.edge_b[grp.edges]]
    homs = _pairs_of(plan, grp.edges, ctx.ncc_cfg.rectify.mode)
    aff1 = aff2 = None
    if ctx.affines is not None and id1 in ctx.affines and id2 in ctx.affines:
        aff1 = np.asarray(ctx.affines[id1])[k1]
        aff2 = np.asarray(ctx.affines[id2])[k2]
    if grp.side == 2:
        return _Call(id1, id2, k1, k2, ctx.pos[id1][k1], ctx.pos[id2][k2], homs, aff1, aff2)
    return _Call(id2, id1, k2, k1, ctx.pos[id2][k2], ctx.pos[id1][k1], np.flip(homs, axis=-3), aff2, aff1)


def _chain(call: _Call, grp: Group, ctx: WalkState) -> None:
    """Record each free node's map from its reference image (:attr:`WalkState.to_ref`)."""
    if ctx.to_ref is None:
        return
    h = call.homs if call.homs.ndim == 4 else call.homs[:, -1]
    m = np.linalg.solve(h[:, 1], h[:, 0])  # fixed-side pixels -> moving-side pixels
    ctx.to_ref[grp.free] = m @ ctx.to_ref[grp.partner]


def predicted(call: _Call) -> np.ndarray:
    """``(n, 2)`` where each match's homography pair puts its fixed keypoint in the moving image."""
    h = call.homs if call.homs.ndim == 4 else call.homs[:, -1]
    m = np.linalg.solve(h[:, 1], h[:, 0])  # fixed-side pixels -> moving-side pixels
    x = np.einsum("nij,nj->ni", m, np.column_stack([call.pts_f, np.ones(len(call.pts_f))]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return x[:, :2] / x[:, 2:3]


def far_moves(call: _Call, new: np.ndarray, moved: np.ndarray, bound_px: float) -> np.ndarray:
    """(n,) bool: the moves to ``new`` (where ``moved``) farther than ``bound_px`` from the
    keypoint's position that have no evidence for them. Evidence is landing within
    ``bound_px`` of where the homography pair predicts the keypoint (:func:`predicted`), or
    bringing it nearer to that prediction: neither the keypoint nor the geometry supports any
    other far peak."""
    pred = predicted(call)
    far_from_kp = np.linalg.norm(new - call.pts_m, axis=1) > bound_px
    dev_new = np.linalg.norm(new - pred, axis=1)
    dev_old = np.linalg.norm(call.pts_m - pred, axis=1)
    nearer = dev_new <= dev_old
    return moved & far_from_kp & ~((dev_new <= bound_px) | nearer)  # NaN: no support


def _apply(grp: Group, call: _Call, new: np.ndarray, moved: np.ndarray, displacement: np.ndarray,
           rejected: np.ndarray, ncc: tuple[np.ndarray, np.ndarray, np.ndarray | None], ctx: WalkState) -> None:
    """Write one group's result: every keypoint is fixed from now on, scored by its NCC after
    (before, where a far move is undone)."""
    st = ctx.stats
    ncc_before, ncc_after = (np.asarray(a, np.float64) for a in ncc[:2])
    if ctx.far_move_px is not None:
        far = far_moves(call, new, moved, ctx.far_move_px)
        if far.any():
            moved = moved & ~far
            rejected = np.asarray(rejected, bool) | far
            ncc_after = np.where(far, ncc_before, ncc_after)
        st["rejected_far"] = st.get("rejected_far", 0) + int(far.sum())
    idx = call.moving_idx
    st["refined"] += grp.size
    st["refined_against_moved"] += int(ctx.moved[grp.partner].sum())
    ctx.pos[call.moving_id][idx[moved]] = new[moved]
    ctx.out_disp[call.moving_id][idx[moved]] = displacement[moved]
    ctx.out_against[call.moving_id][idx, 0] = ctx.plan.node_image[grp.partner]
    ctx.out_against[call.moving_id][idx, 1] = ctx.plan.node_kp[grp.partner]
    _chain(call, grp, ctx)
    ctx.moved[grp.free[moved]] = True
    ctx.score[grp.free] = np.nan_to_num(np.asarray(ncc_after, np.float64), nan=-np.inf)
    st["moved"] += int(moved.sum())
    st["rejected"] += int(np.asarray(rejected).sum())


def _add_counters(res: object, ctx: WalkState) -> None:
    """Add the refiner's least-squares matching counters (if any) to the walk's stats."""
    stats = getattr(res, "stats", None) or {}
    for key in LSM_COUNTERS:
        if key in stats:
            ctx.stats[key] = ctx.stats.get(key, 0) + int(stats[key])


def chunks_by_images(groups: list[Group], max_images: int) -> Iterator[list[Group]]:
    """Consecutive runs of groups that together use at most ``max_images`` images."""
    chunk: list[Group] = []
    ids: set = set()
    for grp in groups:
        mine = set(grp.pair)
        both = ids | mine
        if chunk and len(both) > max_images:
            yield chunk
            chunk, both = [], mine
        chunk.append(grp)
        ids = both
    if chunk:
        yield chunk


def refine_batch(groups: list[Group], ctx: WalkState, device: torch.device) -> None:
    """Refine several groups in one call of the pairwise refiner, on stacked images."""
    from ..warping import ImageStack, to_gray_tensor

    calls, kept = [], []
    for grp in groups:
        if any(ctx.images.get(i) is None for i in grp.pair):
            ctx.stats["skipped"] += grp.size
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
    for i in [i for i in ctx.gray if i not in slot]:  # hold this call's images only
        del ctx.gray[i]
    for i in ids:
        if i not in ctx.gray:
            img = ctx.images.get(i)
            assert img is not None  # groups with a missing image were skipped above
            ctx.gray[i] = to_gray_tensor(img, device)
    stack_f = ImageStack.build([ctx.gray[i] for i in ids], idx_f, device)
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
    _add_counters(res, ctx)
    start = 0
    for grp, call, n in zip(kept, calls, sizes, strict=True):
        seg = slice(start, start + n)
        start += n
        _apply(grp, call, res.pts2[seg], np.asarray(res.moved_side[seg]) == 2,
               np.asarray(res.displacement[seg]), res.rejected[seg],
               (res.ncc_before[seg], res.ncc_after[seg], _seg(res, seg)), ctx)


def _seg(res: object, seg: slice) -> np.ndarray | None:
    """``res.ncc_second[seg]``, or None where the refiner reports no second peak."""
    second = getattr(res, "ncc_second", None)
    return None if second is None else second[seg]


def refine_group(grp: Group, ctx: WalkState) -> None:
    """One refine call: the edges of one group, on its two images."""
    ids = grp.pair
    img_a, img_b = ctx.images.get(ids[0]), ctx.images.get(ids[1])
    if img_a is None or img_b is None:
        ctx.stats["skipped"] += grp.size
        return
    call = _orient(grp, ctx)
    kwargs = {}
    if call.aff_f is not None:
        kwargs = {"affine1": call.aff_f, "affine2": call.aff_m}
    img_f, img_m = (img_a, img_b) if call.fixed_id == ids[0] else (img_b, img_a)
    res = ctx.refine_fn(img_f, img_m, call.pts_f, call.pts_m, call.homs, move="2",
                        config=ctx.ncc_cfg, **kwargs)
    ctx.stats["refine_calls"] += 1
    _add_counters(res, ctx)
    _apply(grp, call, res.pts2, np.asarray(res.moved_side) == 2, np.asarray(res.displacement),
           res.rejected, (res.ncc_before, res.ncc_after, getattr(res, "ncc_second", None)), ctx)
