"""Homography assignment of the kept matches (paper App. A.4). ``"paper"``: the least-error
compatible homography among the top 5 with support at least their median; with exactly two both are
eligible (as in the reference), else the larger plane would always win."""

from __future__ import annotations

import numpy as np

from ..enums import Assignment


def assign_matches(err2: np.ndarray, t_l: float, top: int = 5, *,
                   rule: str | Assignment = Assignment.PAPER,
                   round_inliers: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Labels ``(N,)`` (-1: no compatible homography) and supports ``(K,)`` from the squared errors
    ``err2`` ``(K, N)``; ``round_inliers`` only for ``rule="reference"``. ValueError for a bad rule.
    """
    rule = Assignment.parse(rule, "rule")
    K, N = err2.shape
    labels = np.full(N, -1, dtype=np.int64)
    if K == 0 or N == 0:
        return labels, np.zeros(K, dtype=np.int64)
    kept = np.any(err2 <= t_l**2, axis=0)
    if rule == Assignment.REFERENCE:
        if round_inliers is None or round_inliers.shape != (K, N):
            raise ValueError(f"rule='reference' needs round_inliers of shape {(K, N)}")
        compat = round_inliers & (err2 <= t_l**2)
    else:
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
    if rule != Assignment.MEDIAN:
        q = np.where(m == 2, hi, q)  # two compatible: both eligible, the errors decide
    eligible = compat & (support[:, None] >= q[None, :])
    cost = np.where(eligible, err2, np.inf)
    best = np.argmin(cost, axis=0)
    labels[n_compat > 0] = best[n_compat > 0]
    alone = kept & (n_compat == 0)  # "reference" only: kept, but no round held it
    labels[alone] = np.argmin(err2[:, alone], axis=0)
    return labels, support
