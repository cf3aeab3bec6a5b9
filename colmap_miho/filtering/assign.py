"""Homography assignment of the kept matches (paper App. A.4).

A match is kept iff it is a t_l inlier (with quasi-affinity) of at least one homography.
Among its compatible homographies, take the top 5 by support (their t_l inlier count on the
whole match set), let q be the median of those supports, and assign the homography with the
smallest error among the compatible ones whose support is at least q.
"""

from __future__ import annotations

import numpy as np


def assign_matches(err2: np.ndarray, t_l: float, top: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Assign each match to one homography.

    Args:
        err2: ``(K, N)`` squared MOP errors (``inf`` where quasi-affinity fails).
        t_l: relaxed threshold in pixels.
        top: how many compatible homographies (by support) the median q is taken over.

    Returns:
        ``(labels, support)``: ``labels`` int64 ``(N,)`` index of the assigned homography or
        -1; ``support`` int64 ``(K,)`` t_l inliers of each homography.
    """
    K, N = err2.shape
    labels = np.full(N, -1, dtype=np.int64)
    if K == 0 or N == 0:
        return labels, np.zeros(K, dtype=np.int64)
    compat = err2 <= t_l**2
    support = compat.sum(1).astype(np.int64)
    n_compat = compat.sum(0)
    masked = np.where(compat, support[:, None], -1)
    ranked = -np.sort(-masked, axis=0)  # (K, N) supports, descending, -1 = not compatible
    m = np.minimum(n_compat, top)
    cols = np.arange(N)
    lo = ranked[np.maximum((m - 1) // 2, 0), cols]
    hi = ranked[np.maximum(m // 2, 0), cols]
    q = np.where(m % 2 == 1, lo, (lo + hi) / 2.0)
    eligible = compat & (support[:, None] >= q[None, :])
    cost = np.where(eligible, err2, np.inf)
    best = np.argmin(cost, axis=0)
    labels[n_compat > 0] = best[n_compat > 0]
    return labels, support
