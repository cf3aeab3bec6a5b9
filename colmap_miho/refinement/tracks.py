"""Track-consistent NCC refinement over many images: every keypoint moves at most once.

Pairwise NCC may move either keypoint of a match, so one keypoint would get different
positions in different pairs, which COLMAP cannot store (one position per keypoint index).
Here the refinable matches of all pairs form a graph over (image_id, keypoint_index) nodes;
its connected components are the tracks. Per track one anchor is fixed; the track is walked
breadth-first from the anchor, level by level. Each free keypoint adjacent to an already
fixed one is refined against it (template from the fixed side, ``move`` = the free side) and
becomes fixed whatever the outcome (moved, rejected or skipped). Hence no keypoint moves twice.

Track logic only: the refine calls are made by :mod:`.walk_calls`, the patch maths is in
:mod:`colmap_miho.refinement.ncc`.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .config import NCCConfig, TrackConfig
from .walk_calls import Group, WalkState, chunks_by_images, refine_batch, refine_group

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackRefineResult:
    """Output of :func:`refine_tracks`.

    Attributes:
        keypoints: image_id -> (Ni, 2) float64 refined pixel positions (integer = pixel
            centre), equal to the input where a keypoint was not moved.
        displacement: image_id -> (Ni,) float64 pixels each keypoint moved (0 if not).
        refined_against: image_id -> (Ni, 2) int64 ``(image_id, keypoint_index)`` of the fixed
            keypoint each keypoint was refined against, ``(-1, -1)`` for anchors and keypoints
            that were never refined.
        stats: ``tracks`` (components with >= 2 keypoints), ``conflicting_tracks`` (two
            keypoints of one image in one track), ``keypoints_in_tracks``, ``anchors``,
            ``levels``, ``refined`` (refine attempts), ``moved``, ``rejected``, ``skipped``
            (keypoints left unrefined because an image was missing), ``missing_images``,
            ``refine_calls``, ``images_loaded``, ``seconds``.
    """

    keypoints: dict
    displacement: dict
    refined_against: dict
    stats: dict = field(default_factory=dict)


class _ImageCache:
    """Lazy loader with a bounded LRU cache; ``None`` from the loader means missing."""

    def __init__(self, images, max_items: int, prepare: Callable | None = None):
        self._prepare = prepare
        if isinstance(images, Mapping):
            self._load = images.get
        elif callable(images):
            self._load = images
        else:
            raise ValueError("images must be a Mapping or a callable image_id -> array or None")
        self._cache: OrderedDict = OrderedDict()
        self._max = max_items
        self.loaded = 0
        self.missing: set = set()

    def get(self, image_id):
        if image_id in self.missing:
            return None
        if image_id in self._cache:
            self._cache.move_to_end(image_id)
            return self._cache[image_id]
        img = self._load(image_id)
        if img is None:
            self.missing.add(image_id)
            return None
        self.loaded += 1
        if self._prepare is not None:
            img = self._prepare(img)
        self._cache[image_id] = img
        while len(self._cache) > self._max:
            self._cache.popitem(last=False)
        return img


def match_rows(pair, n_matches: int, result) -> tuple[np.ndarray, np.ndarray]:
    """Per kept match of ``pair`` its label and the patch homography pair.

    Rule: if ``len(result.labels) == n_matches`` the rows correspond 1:1; elif
    ``result.inliers.sum() == n_matches`` the matches are the kept rows in order
    (``labels[inliers]``); else ``ValueError`` naming the pair.

    Returns:
        (labels (M,) int64, -1 = not refinable; homographies (M, 2, 3, 3) float64, identity
        where the label is -1).
    """
    labels = np.asarray(result.labels).astype(np.int64).reshape(-1)
    inliers = np.asarray(result.inliers).astype(bool).reshape(-1)
    if labels.shape[0] != n_matches:
        if inliers.shape[0] == labels.shape[0] and int(inliers.sum()) == n_matches:
            labels = labels[inliers]
        else:
            raise ValueError(
                f"pair {pair}: filter result has {labels.shape[0]} rows and "
                f"{int(inliers.sum())} inliers, but {n_matches} matches were given"
            )
    homs = np.asarray(result.patch_homographies, dtype=np.float64)
    if homs.ndim != 4 or homs.shape[1:] != (2, 3, 3):
        raise ValueError(f"pair {pair}: patch_homographies must be (K, 2, 3, 3), got {homs.shape}")
    bad = (labels >= homs.shape[0]) | (labels < -1)
    if bad.any():
        raise ValueError(f"pair {pair}: labels out of range for {homs.shape[0]} homographies")
    per_match = np.tile(np.eye(3), (n_matches, 2, 1, 1))
    ok = labels >= 0
    per_match[ok] = homs[labels[ok]]
    return labels, per_match


def _resolve_configs(config, ncc_config, track_config) -> tuple[NCCConfig, TrackConfig]:
    ncc, trk = NCCConfig(), TrackConfig()
    if isinstance(config, tuple):
        ncc, trk = config
    elif isinstance(config, NCCConfig):
        ncc = config
    elif isinstance(config, TrackConfig):
        trk = config
    elif config is not None:
        ncc = getattr(config, "ncc", ncc)
        trk = getattr(config, "tracks", trk)
    return (ncc_config or ncc), (track_config or trk)


def refine_tracks(
    images,
    keypoints: Mapping,
    pair_matches: Mapping,
    pair_filter_results: Mapping,
    *,
    config=None,
    ncc_config: NCCConfig | None = None,
    track_config: TrackConfig | None = None,
    affines: Mapping | None = None,
    progress: bool = False,
    on_progress: Callable[[int], None] | None = None,
    refine_fn: Callable | None = None,
) -> TrackRefineResult:
    """Refine keypoints of many images by NCC so that every keypoint moves at most once.

    Args:
        images: a callable ``image_id -> (H, W) gray array (uint8 or float) or None`` or a
            Mapping; None means missing (keypoints needing it are not refined). Images are
            loaded lazily, at most ``TrackConfig.max_images_in_memory`` are kept.
        keypoints: image_id -> (Ni, 2) pixel coordinates (integer = pixel centre).
        pair_matches: (id1, id2) -> (M, 2) int keypoint indices of the kept matches.
        pair_filter_results: (id1, id2) -> ``FilterResult``-like object with ``inliers``,
            ``labels`` and ``patch_homographies`` (K, 2, 3, 3) pairs (A, B), ``A x1 ~ B x2``;
            see :func:`match_rows` for how its rows are aligned with the matches. Matches
            with label -1 are not refined.
        config: a Recipe-like object (``.ncc``, ``.tracks``), a tuple (NCCConfig,
            TrackConfig), or one of the two; ``ncc_config`` / ``track_config`` override it.
            ``NCCConfig.move`` is ignored: the walk decides which side moves.
        affines: optional image_id -> (Ni, 2, 2) keypoint affine frames for the base pass.
        progress: tqdm bar over the keypoints to refine (all keypoints in tracks but the
            anchors).
        on_progress: called with the number of keypoints handled after every refine
            call (worker processes report progress through it).
        refine_fn: the pairwise refiner, default :func:`colmap_miho.refinement.ncc.refine_pair`
            (same signature; tests pass a cheap fake). With ``TrackConfig.batch_pairs`` it
            receives :class:`~.warping.ImageStack` images, the fixed side first, and
            ``move="2"``.

    Anchor rule (``TrackConfig.anchor = "degree"``): the observation with the most
    refinable matches in its track; ties go to the lowest (image_id, keypoint_index). A free
    keypoint adjacent to several fixed ones at one level is refined against the lowest
    (image_id, keypoint_index) of them.

    Returns:
        :class:`TrackRefineResult`.
    """
    t0 = time.perf_counter()
    ncc_cfg, trk_cfg = _resolve_configs(config, ncc_config, track_config)
    prepare, device = None, "cpu"
    default_refiner = refine_fn is None
    if default_refiner:
        from .ncc import refine_pair as refine_fn
        from .ncc import resolve_device
        from .warping import to_gray_tensor

        device = resolve_device(ncc_cfg)
        if device.type == "cuda":
            # keep the cached images on the GPU: each is uploaded once, not once per call
            prepare = lambda img: to_gray_tensor(img, device)  # noqa: E731
    use_batch = trk_cfg.batch_pairs
    if use_batch is None:
        use_batch = default_refiner and str(device).startswith("cuda")
    batched = device if use_batch else None

    image_ids = sorted(keypoints)
    kps = {}
    for i in image_ids:
        arr = np.asarray(keypoints[i], dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"keypoints[{i}] must have shape (N, 2), got {arr.shape}")
        kps[i] = arr
    offset, total = {}, 0
    for i in image_ids:
        offset[i] = total
        total += kps[i].shape[0]
    node_image = np.empty(total, dtype=np.int64)
    node_kp = np.empty(total, dtype=np.int64)
    for i in image_ids:
        sl = slice(offset[i], offset[i] + kps[i].shape[0])
        node_image[sl] = i
        node_kp[sl] = np.arange(kps[i].shape[0])

    # refinable edges: (node_a, node_b, pair index, row)
    pairs = sorted(pair_matches)
    pair_homs, ea, eb, ep, er = [], [], [], [], []
    for p, pair in enumerate(pairs):
        id1, id2 = pair
        if id1 == id2:
            raise ValueError(f"pair {pair}: an image cannot be matched with itself")
        for i in (id1, id2):
            if i not in kps:
                raise ValueError(f"pair {pair}: no keypoints for image {i}")
        m = np.asarray(pair_matches[pair]).astype(np.int64).reshape(-1, 2)
        if pair not in pair_filter_results:
            raise ValueError(f"pair {pair}: no filter result")
        for c, i in ((0, id1), (1, id2)):
            if m.size and (m[:, c].min() < 0 or m[:, c].max() >= kps[i].shape[0]):
                raise ValueError(f"pair {pair}: keypoint index out of range for image {i}")
        labels, homs = match_rows(pair, m.shape[0], pair_filter_results[pair])
        pair_homs.append(homs)
        rows = np.flatnonzero(labels >= 0)
        ea.append(offset[id1] + m[rows, 0])
        eb.append(offset[id2] + m[rows, 1])
        ep.append(np.full(rows.size, p, dtype=np.int64))
        er.append(rows)
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0, np.int64)  # noqa: E731
    ea, eb, ep, er = cat(ea), cat(eb), cat(ep), cat(er)

    out_kp = {i: kps[i].copy() for i in image_ids}
    out_disp = {i: np.zeros(kps[i].shape[0]) for i in image_ids}
    out_against = {i: np.full((kps[i].shape[0], 2), -1, dtype=np.int64) for i in image_ids}
    stats = dict.fromkeys(
        ["tracks", "conflicting_tracks", "keypoints_in_tracks", "anchors", "levels", "refined",
         "moved", "rejected", "skipped", "refine_calls"], 0)

    if total and ea.size:
        graph = coo_matrix((np.ones(ea.size), (ea, eb)), shape=(total, total))
        _, comp = connected_components(graph, directed=False)
        degree = np.bincount(ea, minlength=total) + np.bincount(eb, minlength=total)
        in_track = degree > 0
        comp_nodes = np.flatnonzero(in_track)
        stats["keypoints_in_tracks"] = int(comp_nodes.size)
        track_ids = np.unique(comp[comp_nodes])
        stats["tracks"] = int(track_ids.size)
        img_in_comp = np.unique(np.stack([comp[comp_nodes], node_image[comp_nodes]]), axis=1)
        n_img = np.bincount(img_in_comp[0], minlength=comp.max() + 1)
        n_obs = np.bincount(comp[comp_nodes], minlength=comp.max() + 1)
        stats["conflicting_tracks"] = int((n_obs[track_ids] > n_img[track_ids]).sum())
        # anchors: max degree, ties to the lowest node id (= lowest (image_id, kp index))
        order = np.lexsort((comp_nodes, -degree[comp_nodes], comp[comp_nodes]))
        sorted_comp = comp[comp_nodes][order]
        first = np.ones(order.size, bool)
        first[1:] = sorted_comp[1:] != sorted_comp[:-1]
        anchors = comp_nodes[order[first]]
        stats["anchors"] = int(anchors.size)
        fixed = np.zeros(total, bool)
        fixed[anchors] = True
        cache = _ImageCache(images, trk_cfg.max_images_in_memory, prepare)
        pos = {i: out_kp[i] for i in image_ids}  # updated in place as keypoints move
        bar = None
        to_refine = int(comp_nodes.size - anchors.size)

        def advance(n: int) -> None:
            if bar is not None:
                bar.update(n)
            if on_progress is not None:
                on_progress(n)

        if progress:
            from tqdm import tqdm

            bar = tqdm(total=to_refine, desc="NCC tracks", unit="kp")
        while True:
            fa, fb = fixed[ea], fixed[eb]
            fwd = fa & ~fb  # a fixed, b free: b moves (side 2)
            bwd = fb & ~fa  # b fixed, a free: a moves (side 1)
            if not (fwd.any() or bwd.any()):
                break
            stats["levels"] += 1
            e_idx = np.concatenate([np.flatnonzero(fwd), np.flatnonzero(bwd)])
            free = np.concatenate([eb[fwd], ea[bwd]])
            anchor_of = np.concatenate([ea[fwd], eb[bwd]])
            side = np.concatenate([np.full(fwd.sum(), 2), np.full(bwd.sum(), 1)])
            order = np.lexsort((anchor_of, free))
            keep = np.ones(order.size, bool)
            keep[1:] = free[order][1:] != free[order][:-1]
            sel = order[keep]
            e_idx, free, anchor_of, side = e_idx[sel], free[sel], anchor_of[sel], side[sel]
            groups = np.lexsort((side, ep[e_idx]))
            e_idx, free, anchor_of, side = e_idx[groups], free[groups], anchor_of[groups], side[groups]
            keys = np.stack([ep[e_idx], side], 1)
            bounds = np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1
            groups = [
                Group(pairs[ep[e_idx[g[0]]]], int(side[g[0]]), er[e_idx[g]], free[g],
                       anchor_of[g], pair_homs[ep[e_idx[g[0]]]])
                for g in np.split(np.arange(e_idx.size), bounds)
            ]
            ctx = WalkState(pair_matches, pos, affines, cache, ncc_cfg, refine_fn, node_image,
                             node_kp, out_disp, out_against, stats)
            if batched is not None:
                # groups of one level are independent: each free keypoint is in one group
                # and is refined against keypoints fixed at an earlier level
                for chunk in chunks_by_images(groups, trk_cfg.max_images_in_memory):
                    refine_batch(chunk, ctx, batched)
                    advance(sum(int(grp.rows.size) for grp in chunk))
            else:
                for grp in groups:
                    refine_group(grp, ctx)
                    advance(int(grp.rows.size))
            fixed[free] = True
        if bar is not None:
            bar.close()
        stats["missing_images"] = len(cache.missing)
        stats["images_loaded"] = cache.loaded
    stats["seconds"] = time.perf_counter() - t0
    logger.info("refine_tracks: %s", stats)
    return TrackRefineResult(
        keypoints=out_kp, displacement=out_disp, refined_against=out_against, stats=stats
    )
