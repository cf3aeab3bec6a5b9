"""The track plan: the tracks of every output match, built once for the walk and the workers.

Tracks are the components of all output matches (:mod:`colmap_miho.match_tracks`), the tracks
COLMAP builds from the output. An edge is *refinable* when the filter gave it a patch homography
pair; the others join tracks but never refine. Rules:

- **Anchor**: per track, the node with the most refinable edges (ties: the lowest
  ``(image_id, keypoint_index)``); a track without a refinable edge has none.
- **Reach**: a track is walked from its anchor over refinable edges only; what the anchor
  cannot reach that way never moves, so every moved keypoint is refined to its output track's
  anchor.
- **Conflicts**: a track holding two keypoints of one image more than ``duplicate_px`` apart is
  *frozen* (they cannot be one 3D point); closer ones are duplicates (SIFT's one keypoint per
  orientation) and walked like the others.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ...enums import Rectification
from ...match_tracks import build_tracks, components, distinct, image_runs, node_offsets
from ...types import Pair
from ..config import NCCConfig
from .plan import TrackPlan


def local_affine_of(ncc_cfg: NCCConfig) -> tuple[int, float] | None:
    """The plan's ``local_affine`` argument for an NCC configuration."""
    if ncc_cfg.rectify.mode is Rectification.FILTER:
        return None
    return ncc_cfg.rectify.neighbours, ncc_cfg.rectify.max_residual_px


def _reachable(total: int, ea: np.ndarray, eb: np.ndarray, anchors: np.ndarray,
               nodes: np.ndarray | None = None) -> int:
    """Nodes joined to an anchor by the edges (ea, eb), anchors not counted."""
    if not ea.size:
        return 0
    _, comp = components(ea, eb, total)
    if nodes is None:
        nodes = distinct(np.concatenate([ea, eb]), total)
    hit = np.zeros(comp.max() + 1, bool)
    hit[comp[anchors]] = True
    return int(hit[comp[nodes]].sum() - anchors.size)


def _check_matches(pair: Pair, m: np.ndarray, keypoints: Mapping[int, np.ndarray]) -> np.ndarray:
    m = np.asarray(m)
    if m.ndim != 2 or m.shape[1] != 2:
        if m.size == 0:
            return np.zeros((0, 2), np.int64)
        raise ValueError(f"pair {pair}: matches must have shape (M, 2), got {m.shape}")
    m = m.astype(np.int64)
    id1, id2 = pair
    if id1 == id2:
        raise ValueError(f"pair {pair}: an image cannot be matched with itself")
    for c, i in ((0, id1), (1, id2)):
        if i not in keypoints:
            raise ValueError(f"pair {pair}: no keypoints for image {i}")
        if m.size and (m[:, c].min() < 0 or m[:, c].max() >= keypoints[i].shape[0]):
            raise ValueError(f"pair {pair}: keypoint index out of range for image {i}")
    return m


def pair_rows(pair: Pair, matches: np.ndarray, result: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The output rows of one filtered pair: rows of ``result`` are 1:1 with ``matches``.

    Args:
        pair: (id1, id2), for messages.
        matches: (M, 2) int keypoint indices.
        result: a ``FilterResult``-like object: ``labels`` (M,) int (-1 = no homography),
            ``patch_homographies`` (K, 2, 3, 3), optional ``inliers`` (M,) bool (rows that
            reach the output; all rows when absent).
    Returns:
        (kept matches (M', 2) int64, their labels (M',) int64, homographies (K, 2, 3, 3)
        float64).
    Raises:
        ValueError: rows not 1:1, bad shapes or labels out of range (names the pair).
    """
    labels = np.asarray(result.labels).astype(np.int64).reshape(-1)
    if labels.shape[0] != matches.shape[0]:
        raise ValueError(f"pair {pair}: {labels.shape[0]} filter labels for "
                         f"{matches.shape[0]} matches (rows must be 1:1)")
    inliers = getattr(result, "inliers", None)
    keep = (np.ones(labels.shape[0], bool) if inliers is None
            else np.asarray(inliers).astype(bool).reshape(-1))
    if keep.shape[0] != labels.shape[0]:
        raise ValueError(f"pair {pair}: {keep.shape[0]} inlier flags for "
                         f"{labels.shape[0]} matches (rows must be 1:1)")
    homs = np.asarray(result.patch_homographies, dtype=np.float64)
    if homs.ndim != 4 or homs.shape[1:] != (2, 3, 3):
        raise ValueError(f"pair {pair}: patch_homographies must be (K, 2, 3, 3), got {homs.shape}")
    if ((labels >= homs.shape[0]) | (labels < -1)).any():
        raise ValueError(f"pair {pair}: labels out of range for {homs.shape[0]} homographies")
    return matches[keep], labels[keep], homs


def _nodes(keypoints: Mapping) -> tuple[dict, dict, np.ndarray, np.ndarray]:
    kps = {}
    for i in sorted(keypoints):
        kps[i] = np.asarray(keypoints[i], dtype=np.float64)
        if kps[i].ndim != 2 or kps[i].shape[1] != 2:
            raise ValueError(f"keypoints[{i}] must have shape (N, 2), got {kps[i].shape}")
    offset, _ = node_offsets({i: len(a) for i, a in kps.items()})
    node_image = np.concatenate([np.full(len(a), i, np.int64) for i, a in kps.items()]
                                or [np.zeros(0, np.int64)])
    node_kp = np.concatenate([np.arange(len(a), dtype=np.int64) for a in kps.values()]
                             or [np.zeros(0, np.int64)])
    return kps, offset, node_image, node_kp


def _edges(
    kps: dict[int, np.ndarray],
    offset: dict[int, int],
    pair_matches: Mapping[Pair, np.ndarray],
    pair_filter_results: Mapping[Pair, Any],
    unrefined_matches: Mapping[Pair, np.ndarray] | None,
) -> tuple[tuple[Pair, ...], tuple[np.ndarray, ...], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edge arrays over all output matches, in (pair, row) order."""
    pairs = sorted(set(pair_matches) | set(unrefined_matches or {}))
    homs, ea, eb, ep, el = [], [], [], [], []
    for p, pair in enumerate(pairs):
        ms, ls = [], []
        h = np.zeros((0, 2, 3, 3))
        if pair in pair_matches:
            if pair not in pair_filter_results:
                raise ValueError(f"pair {pair}: no filter result")
            m = _check_matches(pair, pair_matches[pair], kps)
            m, lab, h = pair_rows(pair, m, pair_filter_results[pair])
            ms.append(m)
            ls.append(lab)
        if unrefined_matches and pair in unrefined_matches:
            m = _check_matches(pair, unrefined_matches[pair], kps)
            ms.append(m)
            ls.append(np.full(m.shape[0], -1, np.int64))
        m, lab = np.concatenate(ms), np.concatenate(ls)
        homs.append(h)
        ea.append(offset[pair[0]] + m[:, 0])
        eb.append(offset[pair[1]] + m[:, 1])
        ep.append(np.full(m.shape[0], p, np.int64))
        el.append(lab)
    def cat(xs: list) -> np.ndarray:
        return np.concatenate(xs) if xs else np.zeros(0, np.int64)

    return tuple(pairs), tuple(homs), cat(ea), cat(eb), cat(ep), cat(el)


def _conflicts(track: np.ndarray, nodes: np.ndarray, node_image: np.ndarray, pos: np.ndarray,
               duplicate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(n_tracks,) bool: tracks with two keypoints of one image more than ``duplicate_px``
    apart; and (n_tracks,) bool: tracks with two keypoints of one image at all."""
    n_tracks = int(track.max()) + 1
    order, idx = image_runs(track[nodes], node_image[nodes])
    t, p = track[nodes][order], pos[order]
    count = np.diff(np.append(idx, t.size))
    spread = np.maximum.reduceat(p, idx, axis=0) - np.minimum.reduceat(p, idx, axis=0)
    far = np.linalg.norm(spread, axis=1) > duplicate_px
    any_two = np.zeros(n_tracks, bool)
    any_two[t[idx[count > 1]]] = True
    conflict = np.zeros(n_tracks, bool)
    conflict[t[idx[(count > 1) & far]]] = True
    return conflict, any_two


def build_track_plan(
    keypoints: Mapping,
    pair_matches: Mapping,
    pair_filter_results: Mapping,
    *,
    unrefined_matches: Mapping | None = None,
    duplicate_px: float = 1.0,
    local_affine: tuple[int, float] | None = None,
) -> TrackPlan:
    """The :class:`TrackPlan` of all output matches (the module docstring states the rules).

    Args:
        keypoints: image_id -> (Ni, 2) pixel positions (integer = pixel centre).
        pair_matches: (id1, id2) -> (M, 2) int keypoint indices of a filtered pair.
        pair_filter_results: (id1, id2) -> ``FilterResult``-like, rows 1:1 with
            ``pair_matches`` (see :func:`pair_rows`): ``inliers`` rows reach the output,
            those with a label >= 0 are refinable.
        unrefined_matches: (id1, id2) -> (M, 2) matches that reach the output but carry no
            homography (pairs never filtered, failed, or with a missing image).
        duplicate_px: keypoints of one image in one track closer than this are duplicates,
            farther ones freeze the track.
        local_affine: (k neighbours, max residual px): also give every refinable match its
            own patch homography pair from a local affine fit to its pair's nearest matches
            (:func:`..rectify.local_affine.local_affine_pairs`), fitted when the walk first needs the pair
            (:meth:`TrackPlan.local_pairs`); None: the filter's pairs only.
    Raises:
        ValueError: malformed inputs (names the pair or image).
    """
    kps, offset, node_image, node_kp = _nodes(keypoints)
    pairs, homs, ea, eb, ep, el = _edges(kps, offset, pair_matches, pair_filter_results,
                                         unrefined_matches)
    total = node_image.size
    track = np.full(total, -1, np.int64)
    stats = dict.fromkeys(["tracks", "conflicting_tracks", "frozen_tracks", "frozen_keypoints",
                           "keypoints_in_tracks", "anchors", "unreached_keypoints"], 0)
    stats["unrefinable_matches"] = int((el < 0).sum())
    frozen = np.zeros(total, bool)
    anchors = np.zeros(0, np.int64)
    to_refine = 0
    if ea.size:
        nodes, node_track = build_tracks(ea, eb, total)
        track[nodes] = node_track
        pos = np.concatenate(list(kps.values()))[nodes]
        conflict, any_two = _conflicts(track, nodes, node_image, pos, duplicate_px)
        frozen[nodes] = conflict[track[nodes]]
        stats.update(tracks=int(conflict.size), conflicting_tracks=int(any_two.sum()),
                     frozen_tracks=int(conflict.sum()), frozen_keypoints=int(frozen.sum()),
                     keypoints_in_tracks=int(nodes.size))
        ok = (el >= 0) & ~frozen[ea]
        degree = np.bincount(ea[ok], minlength=total) + np.bincount(eb[ok], minlength=total)
        cand = np.flatnonzero(degree > 0)
        # anchors: most refinable edges, ties to the lowest node (= (image_id, kp index))
        order = np.lexsort((cand, -degree[cand], track[cand]))
        first = np.ones(order.size, bool)
        first[1:] = track[cand][order][1:] != track[cand][order][:-1]
        anchors = cand[order[first]]
        to_refine = _reachable(total, ea[ok], eb[ok], anchors, cand)
        stats["anchors"] = int(anchors.size)
        stats["unreached_keypoints"] = int(
            np.isin(track[nodes], track[anchors]).sum() - anchors.size - to_refine)
    return TrackPlan(keypoints=kps, node_image=node_image, node_kp=node_kp, pairs=pairs,
                     pair_homs=homs, local_homs=None, edge_a=ea, edge_b=eb, edge_pair=ep,
                     edge_row=np.arange(ep.size) - np.searchsorted(ep, ep), edge_label=el,
                     track=track, anchors=anchors, frozen=frozen, to_refine=to_refine,
                     stats=stats,
                     local_affine=None if local_affine is None else tuple(local_affine))
