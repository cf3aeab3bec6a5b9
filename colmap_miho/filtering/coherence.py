"""Plane coherence check: drop kept homographies whose matches are scattered among the matches
of other planes that contradict them (``FilterConfig.coherence``, off by default).

Why: MOP keeps every homography with ``n`` inliers. Where a scene repeats its texture (windows,
bricks, leaves) or mismatches cluster, a handful of wrong matches can agree on a homography of
their own; the plane then overlaps the image area of a large true plane that maps the same
points elsewhere. A true surface is spatially coherent: its matches neighbour each other in
both images. A spurious plane's matches sit among matches of other planes.

Rule, on the kept matches after assignment (App. A.4):

1. For each kept match i (plane ``labels[i]``) look at its ``k`` nearest kept matches in image 1
   and, separately, in image 2. A neighbour *contradicts* i when it is assigned to another
   homography and i is not compatible with that homography (error above t_l, the same
   compatibility test as the keep rule).
2. Match i is *contradicted* when at least ``min_share`` of its neighbours contradict it in
   image 1 **and** in image 2.
3. A homography is dropped when at least ``plane_share`` of its assigned matches are
   contradicted, except the one with the most assigned matches. Its matches are then
   re-assigned among the remaining homographies with the same assignment rule; a match
   compatible with none of them is dropped.

Constants (``k = 8``, ``min_share = 0.75``, ``plane_share = 0.5``) were set once and not
fitted: the ranking of the filters does not depend on them. It is an option because on
multi-plane scenes it also drops a few correct matches; its effect on planar and multi-plane
pairs is measured by ``benchmarks/bench_hard_pairs.py`` and ``benchmarks/bench_filter.py``
(results document).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

NEIGHBOURS = 8
MIN_SHARE = 0.75
PLANE_SHARE = 0.5


def contradicted(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, compatible: np.ndarray,
                 k: int = NEIGHBOURS, min_share: float = MIN_SHARE) -> np.ndarray:
    """Which kept matches are contradicted by their neighbours in both images.

    Args:
        x1, x2: ``(M, 2)`` pixels of the kept matches.
        labels: ``(M,)`` int, each kept match's homography.
        compatible: ``(K, M)`` bool, match m is a t_l inlier of homography k.
        k: neighbours per image.
        min_share: share of the ``k`` neighbours that must contradict, in each image.

    Returns:
        ``(M,)`` bool; all False when there are ``k`` matches or fewer.
    """
    M = len(labels)
    if M <= k:
        return np.zeros(M, dtype=bool)
    cols = np.arange(M)[:, None]
    share = np.ones(M)
    for pts in (x1, x2):
        _, nn = cKDTree(pts).query(pts, k + 1)
        nn = nn[:, 1:]  # the first neighbour is the match itself (or a duplicate point)
        other = labels[nn]
        against = (other != labels[:, None]) & ~compatible[other, cols]
        share = np.minimum(share, against.mean(axis=1))
    return share >= min_share


def incoherent_planes(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, compatible: np.ndarray,
                      plane_share: float = PLANE_SHARE) -> np.ndarray:
    """Indices of the homographies to drop (see the module docstring).

    Args:
        x1, x2: ``(N, 2)`` pixels of all matches.
        labels: ``(N,)`` int, assigned homography or -1 (not kept).
        compatible: ``(K, N)`` bool, t_l compatibility of every match with every homography.
        plane_share: share of a homography's matches that must be contradicted.

    Returns:
        int64 array of homography indices, ascending (empty when all are coherent).
    """
    K = compatible.shape[0]
    kept = np.flatnonzero(labels >= 0)
    if K < 2 or len(kept) == 0:
        return np.zeros(0, dtype=np.int64)
    lab = labels[kept]
    bad = contradicted(x1[kept], x2[kept], lab, compatible[:, kept])
    members = np.bincount(lab, minlength=K)
    hits = np.bincount(lab[bad], minlength=K)
    drop = (members > 0) & (hits >= plane_share * members)
    drop[np.argmax(members)] = False  # the largest plane is what the others are judged against
    return np.flatnonzero(drop).astype(np.int64)
