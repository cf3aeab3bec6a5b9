"""Track-consistent NCC refinement over many images: every keypoint moves at most once.

COLMAP stores one position per keypoint, so pairwise NCC moving either side would conflict. Each
track is walked breadth-first from its anchor (:class:`~.plan.TrackPlan`); a free keypoint next to a
fixed one is refined against it and then fixed whatever the outcome. Several fixed partners: the
anchor, else the best-scoring one, ties to the lowest ``(image_id, index)``."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from ...devices import resolve_device
from ...errors import InvalidInput
from ..config import NCCConfig, TrackConfig
from ..warping import ImageStack, to_frame, to_gray_tensor
from .build import build_track_plan, local_affine_of
from .multiphoto import CHUNK_OBSERVATIONS, MIN_OBSERVATIONS, MULTIPHOTO_COUNTERS, joint_lsm
from .plan import TrackPlan
from .refine_calls import (
    Group,
    Images,
    ImageSource,
    WalkState,
    chunks_by_images,
    refine_batch,
    refine_group,
)

logger = logging.getLogger(__name__)

#: the counters of a walk (summed over worker processes by the pipeline).
WALK_COUNTERS = ("levels", "refined", "refined_against_moved", "moved", "rejected", "rejected_far",
                 "skipped", "refine_calls")


@dataclass(frozen=True)
class TrackRefineResult:
    """Output of :func:`refine_tracks` / :func:`walk_tracks`.

    Attributes:
        keypoints: image_id -> ``(Ni, 2)`` float64 pixel positions (unchanged where not moved).
        displacement: image_id -> ``(Ni,)`` pixels each keypoint moved.
        refined_against: image_id -> ``(Ni, 2)`` ``(image_id, keypoint_index)`` of the partner,
          ``(-1, -1)`` for anchors and keypoints never refined.
        stats: the plan's counts and the walk's (levels, refined, moved, rejected, skipped, ...).
    """

    keypoints: dict
    displacement: dict
    refined_against: dict
    stats: dict = field(default_factory=dict)


def _resolve_configs(config: object, ncc_config: NCCConfig | None,
                     track_config: TrackConfig | None) -> tuple[NCCConfig, TrackConfig]:
    """The NCC and track configs of :func:`refine_tracks`' arguments, each type-checked (InvalidInput)."""
    ncc, trk = NCCConfig(), TrackConfig()
    if isinstance(config, tuple):
        if len(config) != 2:
            raise InvalidInput(f"config as a tuple must be (NCCConfig, TrackConfig), got {len(config)} items")
        ncc, trk = config
    elif isinstance(config, NCCConfig):
        ncc = config
    elif isinstance(config, TrackConfig):
        trk = config
    elif config is not None:
        if not (hasattr(config, "ncc") or hasattr(config, "tracks")):
            raise InvalidInput("config must be a Recipe, an NCCConfig, a TrackConfig or a tuple (NCCConfig, "
                               f"TrackConfig), got {type(config).__name__}")
        ncc = getattr(config, "ncc", ncc)
        trk = getattr(config, "tracks", trk)
    ncc, trk = ncc_config or ncc, track_config or trk
    if not isinstance(ncc, NCCConfig):
        raise InvalidInput(f"the NCC config must be an NCCConfig, got {type(ncc).__name__}")
    if not isinstance(trk, TrackConfig):
        raise InvalidInput(f"the track config must be a TrackConfig, got {type(trk).__name__}")
    return ncc, trk


def refine_tracks(
    images: Images,
    keypoints: Mapping,
    pair_matches: Mapping,
    pair_filter_results: Mapping,
    *,
    unrefined_matches: Mapping | None = None,
    config: object = None,
    ncc_config: NCCConfig | None = None,
    track_config: TrackConfig | None = None,
    affines: Mapping | None = None,
    progress: bool = False,
    on_progress: Callable[[int], None] | None = None,
    refine_fn: Callable | None = None,
) -> TrackRefineResult:
    """Refine keypoints of many images by NCC so that every keypoint moves at most once.

    Args:
        images: ``image_id -> (H, W)`` gray array (uint8 or float) or None (missing), a callable or
          a Mapping.
        keypoints: image_id -> ``(Ni, 2)`` pixels (integer = pixel centre).
        pair_matches: (id1, id2) -> ``(M, 2)`` keypoint indices of a filtered pair.
        pair_filter_results: (id1, id2) -> ``FilterResult``-like (``inliers``, ``labels``,
          ``patch_homographies``), rows 1:1 with ``pair_matches``.
        unrefined_matches: matches that reach the output without a homography: they join tracks
          but never refine.
        config: a Recipe-like object, a ``(NCCConfig, TrackConfig)`` tuple or one of them.
        refine_fn: the pairwise refiner (default :func:`~colmap_miho.refinement.pairwise.refine_pair`).

    Returns a :class:`TrackRefineResult`."""
    ncc_cfg, trk_cfg = _resolve_configs(config, ncc_config, track_config)
    plan = build_track_plan(keypoints, pair_matches, pair_filter_results,
                            unrefined_matches=unrefined_matches,
                            duplicate_px=trk_cfg.duplicate_px,
                            local_affine=local_affine_of(ncc_cfg))
    return walk_tracks(images, plan, ncc_config=ncc_cfg, track_config=trk_cfg, affines=affines,
                       progress=progress, on_progress=on_progress, refine_fn=refine_fn)


def _refiner(refine_fn: Callable | None, ncc_cfg: NCCConfig,
             trk_cfg: TrackConfig) -> tuple[Callable, torch.device | None]:
    """(refine function, device for batched levels or None)."""
    use_batch = trk_cfg.batch_pairs
    if use_batch is None:  # the built-in refiner takes image stacks; a custom one may not
        use_batch = refine_fn is None
    if refine_fn is not None:  # a custom refiner gets its image stacks on the CPU
        if not use_batch:
            return refine_fn, None
        import torch

        return refine_fn, torch.device("cpu")
    from ..pairwise import refine_pair

    device = resolve_device(ncc_cfg.device)
    return refine_pair, (device if use_batch else None)


def _level_groups(plan: TrackPlan, ea: np.ndarray, eb: np.ndarray, e_ids: np.ndarray,
                  fixed: np.ndarray, score: np.ndarray) -> list[Group] | None:
    """The next level's groups: each free node with a fixed neighbour paired with its best one
    (ties: lowest id), grouped by (pair, side); None when there are none."""
    fa, fb = fixed[ea], fixed[eb]
    fwd = fa & ~fb  # a fixed, b free: b moves (side 2)
    bwd = fb & ~fa  # b fixed, a free: a moves (side 1)
    if not (fwd.any() or bwd.any()):
        return None
    e_idx = np.concatenate([e_ids[fwd], e_ids[bwd]])
    free = np.concatenate([eb[fwd], ea[bwd]])
    partner = np.concatenate([ea[fwd], eb[bwd]])
    side = np.concatenate([np.full(int(fwd.sum()), 2), np.full(int(bwd.sum()), 1)])
    order = np.lexsort((partner, -score[partner], free))
    keep = np.ones(order.size, bool)
    keep[1:] = free[order][1:] != free[order][:-1]
    sel = order[keep]
    e_idx, free, partner, side = e_idx[sel], free[sel], partner[sel], side[sel]
    pair = plan.edge_pair[e_idx]
    order = np.lexsort((side, pair))
    e_idx, free, partner, side, pair = (a[order] for a in (e_idx, free, partner, side, pair))
    bounds = np.flatnonzero((pair[1:] != pair[:-1]) | (side[1:] != side[:-1])) + 1
    return [Group(plan.pairs[int(pair[g[0]])], int(side[g[0]]), e_idx[g], free[g], partner[g])
            for g in np.split(np.arange(e_idx.size), bounds)]


def cache_order(groups: list[Group], level: int) -> list[Group]:
    """A level's calls in an order that reuses images (a snake over pairs, reversed every other
    level), so an LRU image cache decodes fewer images; calls of a level are independent, so no
    result changes."""
    firsts = sorted({grp.pair[0] for grp in groups})
    rank = {i: r for r, i in enumerate(firsts)}

    def key(grp: Group) -> tuple:
        id1, id2 = grp.pair
        return (rank[id1], id2 if rank[id1] % 2 == 0 else -id2, grp.side)

    out = sorted(groups, key=key)
    return out[::-1] if level % 2 else out


def walk_tracks(
    images: Images,
    plan: TrackPlan,
    *,
    ncc_config: NCCConfig | None = None,
    track_config: TrackConfig | None = None,
    affines: Mapping | None = None,
    progress: bool = False,
    on_progress: Callable[[int], None] | None = None,
    refine_fn: Callable | None = None,
) -> TrackRefineResult:
    """Walk the tracks of ``plan`` (see :func:`refine_tracks` for the arguments)."""
    t0 = time.perf_counter()
    ncc_cfg, trk_cfg = ncc_config or NCCConfig(), track_config or TrackConfig()
    refine_fn, batched = _refiner(refine_fn, ncc_cfg, trk_cfg)
    kps = plan.keypoints
    out_kp = {i: k.copy() for i, k in kps.items()}
    out_disp = {i: np.zeros(k.shape[0]) for i, k in kps.items()}
    out_against = {i: np.full((k.shape[0], 2), -1, dtype=np.int64) for i, k in kps.items()}
    stats = dict(plan.stats, **dict.fromkeys(WALK_COUNTERS, 0))
    source = ImageSource(images)
    decodes_before = getattr(images, "decodes", None)
    ok = plan.refinable()
    e_ids = np.flatnonzero(ok)
    ea, eb = plan.edge_a[ok], plan.edge_b[ok]
    fixed = np.zeros(plan.num_nodes, bool)
    fixed[plan.anchors] = True
    score = np.full(plan.num_nodes, -np.inf)
    score[plan.anchors] = np.inf
    to_ref = None
    if trk_cfg.multiphoto_lsm:  # each node's chain from its anchor
        to_ref = np.full((plan.num_nodes, 3, 3), np.nan)
        to_ref[plan.anchors] = np.eye(3)
    far_px = None
    if trk_cfg.far_move_check:
        far_px = ncc_cfg.rectify.max_residual_px
    ctx = WalkState(plan, out_kp, affines, source, ncc_cfg, refine_fn, score,
                    np.zeros(plan.num_nodes, bool), out_disp, out_against, stats, to_ref=to_ref,
                    far_move_px=far_px)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=plan.to_refine, desc="NCC tracks", unit="kp")

    def advance(n: int) -> None:
        if bar is not None:
            bar.update(n)
        if on_progress is not None:
            on_progress(n)

    try:
        while (groups := _level_groups(plan, ea, eb, e_ids, fixed, score)) is not None:
            stats["levels"] += 1
            if batched is not None:
                # groups of one level are independent: each free keypoint is in one group
                # and is refined against keypoints fixed at an earlier level
                for chunk in chunks_by_images(groups, trk_cfg.max_images_in_memory):
                    refine_batch(chunk, ctx, batched)
                    advance(sum(grp.size for grp in chunk))
            else:
                for grp in cache_order(groups, stats["levels"]):
                    refine_group(grp, ctx)
                    advance(grp.size)
            for grp in groups:
                fixed[grp.free] = True
        if trk_cfg.multiphoto_lsm:
            joint_pass(ctx, batched or resolve_device(ncc_cfg.device), trk_cfg.multiphoto_iterations)
    finally:
        if bar is not None:
            bar.close()
    stats["missing_images"] = len(source.missing)
    stats["images_loaded"] = len(source.used)
    if isinstance(decodes_before, int):
        stats["image_decodes"] = int(getattr(images, "decodes", 0)) - decodes_before
    stats["seconds"] = time.perf_counter() - t0
    logger.info("refine_tracks: %s", stats)
    return TrackRefineResult(keypoints=out_kp, displacement=out_disp,
                             refined_against=out_against, stats=stats)


def joint_pass(ctx: WalkState, device: torch.device, iterations: int) -> None:
    """Run :func:`joint_lsm` on the tracks the walk reached (at least :data:`MIN_OBSERVATIONS`
    chained keypoints) and write the accepted moves and stats into ``ctx``."""
    t0 = time.perf_counter()
    for key in MULTIPHOTO_COUNTERS:
        ctx.stats.setdefault(key, 0)
    try:
        _joint_tracks(ctx, device, iterations)
    finally:
        ctx.stats["joint_seconds"] += time.perf_counter() - t0


def _joint_tracks(ctx: WalkState, device: torch.device, iterations: int) -> None:
    """The body of :func:`joint_pass`."""
    plan, to_ref = ctx.plan, ctx.to_ref
    if to_ref is None or plan.anchors.size == 0:
        return
    reach = np.isfinite(to_ref).all(axis=(1, 2)) & (plan.track >= 0)
    anchor_of_track = np.full(int(plan.track.max(initial=-1)) + 1, -1, np.int64)
    anchor_of_track[plan.track[plan.anchors]] = plan.anchors
    nodes = np.flatnonzero(reach)
    loaded = {i: ctx.images.get(i) for i in np.unique(plan.node_image[nodes]).tolist()}
    gray = {i: ctx.gray[i] if i in ctx.gray else to_gray_tensor(img, device)
            for i, img in loaded.items() if img is not None}  # each image converted once
    del loaded
    nodes = nodes[np.isin(plan.node_image[nodes], list(gray))]
    trk = plan.track[nodes]
    is_ref = anchor_of_track[trk] == nodes
    has_ref = np.zeros(anchor_of_track.size, bool)
    has_ref[trk[is_ref]] = True
    n_obs = np.bincount(trk, minlength=anchor_of_track.size)
    keep = has_ref[trk] & (n_obs[trk] >= MIN_OBSERVATIONS)
    nodes, trk, is_ref = nodes[keep], trk[keep], is_ref[keep]
    if nodes.size == 0:
        return
    order = np.argsort(trk, kind="stable")
    nodes, trk, is_ref = nodes[order], trk[order], is_ref[order]
    bounds = np.flatnonzero(np.diff(trk)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [trk.size]])
    lo = 0
    while lo < starts.size:  # chunks of whole tracks
        hi = lo + 1
        while hi < starts.size and ends[hi] - starts[lo] <= CHUNK_OBSERVATIONS:
            hi += 1
        seg = slice(int(starts[lo]), int(ends[hi - 1]))
        _joint_chunk(ctx, gray, nodes[seg], trk[seg], is_ref[seg], iterations, anchor_of_track)
        lo = hi


def _joint_chunk(ctx: WalkState, gray: dict, nodes: np.ndarray, trk: np.ndarray, is_ref: np.ndarray,
                 iterations: int, anchor_of_track: np.ndarray) -> None:
    """One batched :func:`joint_lsm` call over whole tracks (``nodes`` grouped by track) on
    the images ``gray`` (image id -> (H, W) float32 tensor), ``iterations`` consensus passes."""
    plan = ctx.plan
    assert ctx.to_ref is not None
    img_of, kp_of = plan.node_image[nodes], plan.node_kp[nodes]
    anchor = anchor_of_track[trk]
    pos = np.stack([ctx.pos[int(i)][int(k)] for i, k in zip(img_of, kp_of, strict=True)])
    c = np.stack([ctx.pos[int(i)][int(k)] for i, k in
                  zip(plan.node_image[anchor], plan.node_kp[anchor], strict=True)])
    H = ctx.to_ref[nodes].copy()
    ch = np.einsum("nij,nj->ni", H, np.concatenate([c, np.ones((c.shape[0], 1))], axis=1))
    d = pos - ch[:, :2] / ch[:, 2:]
    Td = np.tile(np.eye(3), (nodes.size, 1, 1))
    Td[:, :2, 2] = d
    H = Td @ H  # the chain, translated to the walk's position
    ids = list(dict.fromkeys(img_of.tolist()))
    slot = {i: k for k, i in enumerate(ids)}
    device = gray[ids[0]].device
    stack = ImageStack.build([gray[i] for i in ids], [slot[i] for i in img_of.tolist()], device)
    _, tr_local = np.unique(trk, return_inverse=True)
    f64 = torch.float64
    H_t = torch.as_tensor(H, dtype=f64, device=device)
    c_t = torch.as_tensor(c, dtype=f64, device=device)
    res = joint_lsm(stack, H_t, c_t, torch.as_tensor(tr_local, dtype=torch.int64, device=device),
                    torch.as_tensor(is_ref, device=device), ctx.ncc_cfg, iterations)
    new = to_frame(H_t, c_t + res.shift).cpu().numpy()
    acc = res.accepted.cpu().numpy()
    st = ctx.stats
    st["joint_tracks"] += int(np.unique(trk).size)
    st["joint_observations"] += int((~is_ref).sum())
    for key, val in res.counts.items():
        st[key] += int(val)
    for o in np.flatnonzero(acc):
        i, k = int(img_of[o]), int(kp_of[o])
        ctx.pos[i][k] = new[o]
        ctx.out_disp[i][k] = float(np.linalg.norm(new[o] - plan.keypoints[i][k]))
        ctx.out_against[i][k] = (plan.node_image[anchor[o]], plan.node_kp[anchor[o]])
