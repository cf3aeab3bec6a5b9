"""One RANSAC run of MOP (App. A.3), batched and guided: hypotheses are fully scored in order of
their one-way bound until none can beat the best, so the result is what exhaustive scoring would
give. Only samples that pass the spread test count as iterations."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .compiled import ransac as kernels
from .compiled import scoring as scoring_kernels
from .config import FilterConfig
from .homography import adjugate, dlt
from .problem import Hypotheses, Problem
from .sampling import LocalCandidates, Sampler, required_iters
from .scoring import NumpyScoring, sample_signs

_DRAW_CAP = 10  # most draws per RANSAC run, in units of c_max


@dataclass
class RoundResult:
    """Best model of one run: ``hyp``, ``err2`` ``(n_pool,)`` squared errors, ``count`` t_l inliers."""

    hyp: Hypotheses
    err2: np.ndarray
    count: int
    stats: dict = field(default_factory=dict)


def _greedy_buffer(cands: list[tuple[Hypotheses, int, np.ndarray]], best_mask: np.ndarray,
                   z: int, compiled: bool = False):
    """Top-z sub-optimal models ordered by inliers not covered by the best and better ones (App. A.3)."""
    if z == 0 or not cands:
        return []
    masks = np.stack([m for _, _, m in cands])
    if compiled:
        return [cands[k][0].row(cands[k][1])
                for k in kernels.greedy_cover(masks, best_mask, z).tolist()]
    covered = best_mask.copy()
    chosen = []
    free = np.ones(len(cands), dtype=bool)
    for _ in range(min(z, len(cands))):
        gain = np.where(free, np.count_nonzero(masks & ~covered, axis=1), -1)
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(cands[k][0].row(cands[k][1]))
        covered |= masks[k]
        free[k] = False
    return chosen


@dataclass
class _Search:
    """State of one RANSAC run: the best model so far (``count`` -1 before any) and the sub-optimal
    candidates for the top-z buffer."""

    t2: float
    hyp: Hypotheses | None = None
    err: np.ndarray | None = None
    count: int = -1
    mask: np.ndarray | None = None
    cands: list[tuple[Hypotheses, int, np.ndarray]] = field(default_factory=list)

    def consider(self, hyp: Hypotheses, masks: np.ndarray, err: np.ndarray | None = None,
                 rows: np.ndarray | None = None) -> bool:
        """Take fully scored hypotheses' inlier ``masks`` ``(K, n_pool)`` (and ``err`` when at
        hand); whether the best changed. A replaced best and others with inliers become candidates."""
        counts = masks.sum(axis=1)
        improved = False
        for k in np.argsort(-counts, kind="stable").tolist():
            row = k if rows is None else int(rows[k])
            if counts[k] > self.count:
                if self.hyp is not None and self.mask is not None:  # set together
                    self.cands.append((self.hyp, 0, self.mask))
                self.hyp, self.err = hyp.row(row), None if err is None else err[k]
                self.count, self.mask = int(counts[k]), masks[k]
                improved = True
            elif counts[k] > 0:
                self.cands.append((hyp, row, masks[k]))
        return improved


def _required(search: _Search, sampler: Sampler, n: int, cfg: FilterConfig) -> float:
    """Adaptive iteration bound for the current best model (``max_iters`` before any)."""
    if search.count <= 0:
        return float(cfg.iteration_cap)
    return required_iters(search.count / n, sampler.local_inlier_fraction(search.mask, search.count),
                           sampler.fraction, cfg.confidence)


class _BatchScores:
    """Full scores of one batch's hypotheses in the order of their one-way bound, computed on
    demand; ``prefetch > 0`` screens ahead in doubling chunks with the same result."""

    def __init__(self, scoring: NumpyScoring, problem: Problem, hyp: Hypotheses,
                 order: np.ndarray, ub: np.ndarray, pool: np.ndarray, cfg: FilterConfig,
                 t2: float, reach: int) -> None:
        self.scoring, self.problem, self.hyp, self.ub = scoring, problem, hyp, ub
        self.order = order
        self.pool, self.cfg, self.t2, self.reach = pool, cfg, t2, reach
        self.chunk = scoring.prefetch
        self.done = 0
        if self.chunk:
            self.sv = np.zeros(reach, dtype=bool)
            self.mask = np.zeros((reach, len(pool)), dtype=bool)

    def at(self, pos: np.ndarray) -> Hypotheses:
        """The hypotheses at positions ``pos`` of the order."""
        return self.hyp.take(self.order[pos])

    def get(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(keep, masks, err)`` at ``pos``: singular-value test, inlier masks and errors if at hand."""
        if not self.chunk:
            keep = pos[self.scoring.singular_value_ok(self.problem, self.at(pos), self.cfg)]
            if not len(keep):
                return keep, np.zeros((0, len(self.pool)), dtype=bool), None
            masks, err = self.scoring.masks(self.problem, self.at(keep), self.pool, self.t2)
            return keep, masks, err
        if len(pos) and pos[-1] >= self.done:
            stop = min(max(int(pos[-1]) + 1, self.done + self.chunk), self.reach)
            todo = np.arange(self.done, stop)
            todo = todo[self.ub[todo] > 0]
            if len(todo):
                self.sv[todo], self.mask[todo] = self.scoring.screen(
                    self.problem, self.at(todo), self.pool, self.t2, self.cfg)
            self.done = stop
            self.chunk *= 2
        keep = pos[self.sv[pos]]
        return keep, self.mask[keep], None


def _score_batch(problem: Problem, hyp: Hypotheses, ub: np.ndarray, pool: np.ndarray,
                 cfg: FilterConfig, search: _Search, stats: dict, scoring: NumpyScoring) -> bool:
    """Full-score the batch's hypotheses that can matter, by descending bound ``ub``; the two
    strongest are always scored as buffer candidates. Returns whether the best changed."""
    if scoring.compiled:
        return _score_batch_compiled(problem, hyp, ub, pool, cfg, search, stats, scoring)
    order = np.argsort(-ub, kind="stable")
    ub = ub[order]
    n_buf = int(np.count_nonzero(ub[: min(2, cfg.buffer_size)] >= cfg.inlier_count))
    # The best count only rises, so no group starting past the bounds above it is reached.
    first = max(int(np.count_nonzero(ub > search.count)), n_buf)
    reach = min(len(ub), -(-first // 4) * 4)
    scores = _BatchScores(scoring, problem, hyp, order, ub, pool, cfg, search.t2, reach)
    improved = False
    start = 0
    while start < len(order) and (ub[start] > search.count or start < n_buf):
        pos = np.arange(start, min(start + 4, len(order)))
        start += 4
        keep, masks, err = scores.get(pos[ub[pos] > 0])
        if not len(keep):
            continue
        stats["full_scored"] += len(keep)
        improved |= search.consider(scores.hyp, masks, err, rows=scores.order[keep])
    return improved


def _score_batch_compiled(problem: Problem, hyp: Hypotheses, ub: np.ndarray, pool: np.ndarray,
                          cfg: FilterConfig, search: _Search, stats: dict,
                          scoring: NumpyScoring) -> bool:
    """:func:`_score_batch` in one compiled call (the same hypotheses, candidates and best)."""
    order, masks, events, best, count, scored = scoring.score_batch(
        problem, hyp, ub, pool, cfg, search.t2, search.count, search.hyp is not None)
    stats["full_scored"] += scored
    cands = search.cands
    for p in events.tolist():
        if p < 0:  # the best from before the batch (only when there was one)
            assert search.hyp is not None and search.mask is not None
            cands.append((search.hyp, 0, search.mask))
        else:
            cands.append((hyp, int(order[p]), masks[p]))
    if best < 0:
        return False
    search.hyp, search.err = hyp.row(int(order[best])), None
    search.count, search.mask = int(count), masks[best]
    return True


def _refit_best(problem: Problem, pool: np.ndarray, cfg: FilterConfig, search: _Search,
                stats: dict, scoring: NumpyScoring) -> None:
    """Replace the best by least-squares refits on its inliers while they lose none."""
    assert search.hyp is not None and search.mask is not None, "no best model"
    for _ in range(cfg.refit_iters):
        refit = _refit(problem, search.hyp, pool[search.mask], scoring.compiled)
        if refit is None:
            break
        err = scoring.error_sq(problem, refit, pool)[0]
        mask = err <= search.t2
        count = int(mask.sum())
        stats["full_scored"] += 1
        if count < search.count:
            break
        unchanged = count == search.count and np.array_equal(mask, search.mask)
        search.hyp, search.err, search.count, search.mask = refit, err, count, mask
        if unchanged:
            break


def ransac_round(problem: Problem, pool: np.ndarray, cfg: FilterConfig, rng: np.random.Generator,
                 buffer: list[Hypotheses], candidates: LocalCandidates | None = None,
                 scoring: NumpyScoring | None = None
                 ) -> tuple[RoundResult | None, list[Hypotheses]]:
    """One RANSAC search on ``pool`` ``(n,)``; the top-z ``buffer`` is evaluated first and returned
    updated. Returns ``(result or None, buffer)``."""
    n = len(pool)
    stats: dict[str, float] = {"drawn": 0, "samples": 0, "valid": 0, "full_scored": 0}
    if n < 4:
        return None, buffer
    scoring = NumpyScoring() if scoring is None else scoring
    search = _Search(t2=cfg.t_l**2)
    if buffer:
        boot = Hypotheses.concat(buffer)
        search.consider(boot, *scoring.masks(problem, boot, pool, search.t2))
        stats["full_scored"] += len(boot)
    sampler = Sampler(problem, pool, cfg, candidates, compiled=scoring.compiled)
    required = _required(search, sampler, n, cfg)
    last = cfg.batch_size
    # Iterations are the samples that pass the spread test: a draw that fails it is not a
    # hypothesis and counts neither towards c_min / c_max nor against the adaptive bound
    # (samples rejected by the reflection or quasi-affinity checks do count: they are
    # hypotheses found wrong). A pool where almost no sample is spread out stops after
    # _DRAW_CAP x c_max draws.
    cap = cfg.iteration_cap
    while (stats["samples"] < (target := max(cfg.min_iters, min(required, cap)))
           and stats["drawn"] < _DRAW_CAP * cap):
        # Small batches while the bound may still drop, bigger ones when it will not; sized
        # by the share of spread-out draws so far, growing by at most batch_growth.
        size = cfg.batch_size
        if search.count > 0:
            rate = max(stats["samples"] / max(stats["drawn"], 1), 0.05)
            most = 8 * size if not cfg.batch_growth else min(8 * size, last * cfg.batch_growth)
            size = int(min(max(size, (target - stats["samples"]) / rate), most))
        last = size
        sample = sampler.draw(rng, size)
        stats["drawn"] += size
        ok = scoring.spread_ok(problem, sample, cfg.t_l)
        stats["samples"] += int(ok.sum())
        hyp, ub = scoring.hypotheses(problem, sample, cfg, ok, pool, search.t2)
        stats["valid"] += len(hyp)
        if len(hyp) and _score_batch(problem, hyp, ub, pool, cfg, search, stats, scoring):
            required = _required(search, sampler, n, cfg)
    if search.hyp is None:
        return None, buffer
    _refit_best(problem, pool, cfg, search, stats, scoring)
    if search.err is None:  # the scoring kept only masks: the best's errors, once
        search.err = scoring.error_sq(problem, search.hyp, pool)[0]
    assert search.mask is not None  # set together with hyp
    buffer = _greedy_buffer(search.cands, search.mask, cfg.buffer_size, scoring.compiled)
    stats["required_iters"] = required
    return RoundResult(search.hyp, search.err, search.count, stats), buffer


def _refit(problem: Problem, hyp: Hypotheses, idx: np.ndarray,
           compiled: bool = False) -> Hypotheses | None:
    """Least-squares normalised DLT of every half on ``idx``; None when degenerate or when the
    sample loses its quasi-affine consistency."""
    if len(idx) < 5:
        return None
    if compiled:
        ok, H, Hinv, sign, sign_inv = scoring_kernels.refit(idx, problem.src_all, problem.dst_all,
                                                    hyp.sample[0])
        if not ok:
            return None
        return Hypotheses(H[None], Hinv[None], sign[None], sign_inv[None], hyp.sample.copy())
    # Every half in one batched fit: contiguous per half, the same bits as one fit each (a
    # strided copy would change the order of the centroid's sums).
    src = np.ascontiguousarray(np.take(problem.src_all, idx, axis=0).transpose(1, 0, 2))
    dst = np.ascontiguousarray(np.take(problem.dst_all, idx, axis=0).transpose(1, 0, 2))
    H = dlt(src, dst)[0][None]  # (1, halves, 3, 3)
    if not np.all(np.isfinite(H)):
        return None
    Hinv = adjugate(H)
    ok, sign, sign_inv = sample_signs(problem, H, Hinv, hyp.sample)
    if not ok[0]:
        return None
    return Hypotheses(H, Hinv, sign, sign_inv, hyp.sample.copy())
