"""Plane coherence check (``FilterConfig.coherence``, off by default): a homography is dropped when
most of its matches sit, in both images, among matches of other planes they do not fit (a true
surface's matches neighbour each other; a few wrong matches agreeing on a plane do not)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

NEIGHBOURS = 8
MIN_SHARE = 0.75
PLANE_SHARE = 0.5


def contradicted(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, compatible: np.ndarray,
                 k: int = NEIGHBOURS, min_share: float = MIN_SHARE) -> np.ndarray:
    """``(M,)`` bool: kept matches contradicted by their neighbours in both images (all False with
    ``k`` matches or fewer); ``compatible`` ``(K, M)``: t_l inliers per homography."""
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
    """Ascending indices of the homographies to drop; ``labels`` ``(N,)`` (-1: not kept)."""
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
