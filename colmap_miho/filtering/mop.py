"""MOP's outer loop: multiple planes by sequential RANSAC (paper Sec. 3.1, App. A.2), stopping after
``max_failures`` failed rounds in a row (the reference's rule is ``max_failures=4``)."""

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
    """Kept hypotheses in discovery order, each one's t_l inliers in its round's pool ``(K, N)``, counters."""

    hyps: Hypotheses
    round_inliers: np.ndarray
    stats: dict = field(default_factory=dict)


def run_mop(problem: Problem, cfg: FilterConfig, rng: np.random.Generator,
            progress: bool = False, scoring: NumpyScoring | None = None) -> MopOutput:
    """Find the homographies of ``problem``; ``scoring`` runs the heavy kernels (None: numpy)."""
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
