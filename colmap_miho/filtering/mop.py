"""MOP's outer loop: multiple overlapping planes by sequential RANSAC (paper Sec. 3.1, App. A.2).

Each round runs :func:`~colmap_miho.filtering.ransac.ransac_round` on the current pool with
the relaxed threshold t_l. A best model with fewer than n inliers is a failure and is not
kept. Otherwise it is kept and its strict (t_h) inliers leave the pool when there are more
than n/2 of them; if not, its relaxed (t_l) inliers leave and the round counts as a failure.
A round without failure resets the counter; MOP stops when ``max_failures`` (c_f*) failures
happen in a row (the paper's rule; the reference implementation stops one later, which is
``max_failures=4``) or when fewer than n matches are left (no round could succeed).

The reference has an extra rule: when a round's strict inliers shrink the pool by at most
n/2 matches, it counts a failure and removes from the pool the relaxed (t_l) inliers of
*every* homography kept so far, not only this one's. Here, as in the paper, such a round
removes this model's relaxed inliers (>= n of them) and counts a failure; the extra rule's
condition can then never hold, and the union it would remove is not implemented.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..enums import Sampling
from .config import FilterConfig
from .problem import Hypotheses, Problem
from .ransac import ransac_round
from .sampling import LocalCandidates
from .scoring import NumpyScoring

logger = logging.getLogger(__name__)


@dataclass
class MopOutput:
    """Kept hypotheses (``K`` of them, in discovery order), each one's t_l inliers in the pool
    of its round (``round_inliers``, bool ``(K, N)``) and loop counters."""

    hyps: Hypotheses
    round_inliers: np.ndarray
    stats: dict = field(default_factory=dict)


def run_mop(problem: Problem, cfg: FilterConfig, rng: np.random.Generator,
            progress: bool = False, scoring: NumpyScoring | None = None) -> MopOutput:
    """Find the homographies of ``problem`` (all matches ``0..N-1`` start in the pool);
    ``scoring`` runs the heavy RANSAC kernels (``None``: numpy)."""
    n_req = cfg.inlier_count
    t_h2 = cfg.strict_threshold**2
    pool = np.arange(len(problem.x1))
    buffer: list[Hypotheses] = []
    kept: list[Hypotheses] = []
    held: list[np.ndarray] = []
    failures = 0
    candidates = (LocalCandidates(problem, cfg, compiled=getattr(scoring, "compiled", False))
                  if cfg.sampling == Sampling.LOCAL else None)
    stats = {"rounds": 0, "failures": 0, "drawn": 0, "samples": 0, "valid": 0, "full_scored": 0}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc="MOP rounds", unit="round", leave=False)
    # A model needs n inliers among the pool: with fewer matches left no round can succeed,
    # so stopping there gives the same result as running out the failure counter.
    while failures < cfg.max_failures and len(pool) >= max(4, n_req):
        res, buffer = ransac_round(problem, pool, cfg, rng, buffer, candidates, scoring)
        stats["rounds"] += 1
        if bar is not None:
            bar.update(1)
        if res is None:
            failures += 1
            stats["failures"] += 1
            continue
        for key in ("drawn", "samples", "valid", "full_scored"):
            stats[key] += res.stats[key]
        if res.count < n_req:
            failures += 1
            stats["failures"] += 1
            continue
        strict = res.err2 <= t_h2
        if strict.sum() > n_req / 2:
            remove = strict
            failures = 0
        else:
            remove = res.err2 <= cfg.t_l**2
            failures += 1
            stats["failures"] += 1
        kept.append(res.hyp)
        held.append(pool[res.err2 <= cfg.t_l**2])
        pool = pool[~remove]
        logger.debug("MOP round %d: %d inliers, %d left in pool", stats["rounds"], res.count,
                     len(pool))
    if bar is not None:
        bar.close()
    hyps = Hypotheses.concat(kept) if kept else Hypotheses.empty(problem.num_halves)
    stats["homographies"] = len(hyps)
    round_inliers = np.zeros((len(held), len(problem.x1)), dtype=bool)
    for k, idx in enumerate(held):
        round_inliers[k, idx] = True
    return MopOutput(hyps, round_inliers, stats)
