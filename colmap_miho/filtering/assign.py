"""Homography assignment of the kept matches (paper App. A.4).

A match is kept iff it is a t_l inlier (with quasi-affinity) of at least one homography; it
is then *compatible* with those homographies. Rules (``FilterConfig.assignment``):

- ``"paper"`` (default): among the compatible homographies take the top 5 by support (t_l
  inliers on the whole match set), let q be the median of their supports, and assign the
  compatible homography with the smallest error among those whose support is at least q.
  With exactly two compatible homographies both are eligible, so the one with the smaller
  error wins: the plain median of two supports is their mean, which would always pick the
  larger plane and turn the paper's "intermediate solution" between least error and largest
  support into the largest-support rule. This is also what the reference implementation
  does (its median index is rounded up to the second entry when two are compatible).
- ``"median"``: the plain median in every case (two compatible: the larger plane).
- ``"reference"``: the reference implementation's rule: compatibility and supports come from
  each homography's t_l inliers in the pool of the MOP round that found it (matches removed
  by earlier rounds are not compatible with later homographies), q as in ``"paper"``, and a
  kept match compatible with none of them gets its least-error homography. The kept set is
  the same as with ``"paper"``; only the labels (and so the NCC patch frames) differ.

For 1, 3, 4 or 5 compatible homographies ``"paper"``, ``"median"`` and ``"reference"`` (given
the same compatibility) choose alike: q is the top support, the 2nd, the mean of the 2nd and
3rd (eligible: the top two, and the 3rd only on a tie), and the 3rd.
"""

from __future__ import annotations

import numpy as np

from ..enums import Assignment


def assign_matches(err2: np.ndarray, t_l: float, top: int = 5, *,
                   rule: str | Assignment = Assignment.PAPER,
                   round_inliers: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Assign each match to one homography.

    Args:
        err2: ``(K, N)`` squared MOP errors (``inf`` where quasi-affinity fails), in pixels^2.
        t_l: relaxed threshold in pixels.
        top: how many compatible homographies (by support) the median q is taken over.
        rule: ``"paper"``, ``"median"`` or ``"reference"`` (see the module docstring).
        round_inliers: ``(K, N)`` bool, each homography's t_l inliers in the pool of the
            round that found it; required by ``rule="reference"``, ignored otherwise.

    Returns:
        ``(labels, support)``: ``labels`` int64 ``(N,)`` index of the assigned homography or
        -1 (compatible with none); ``support`` int64 ``(K,)`` the supports the rule used
        (t_l inliers on all matches, or in the round's pool for ``"reference"``).

    Raises:
        ValueError: unknown ``rule``, or ``"reference"`` without ``round_inliers`` of shape
            ``(K, N)``.
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
