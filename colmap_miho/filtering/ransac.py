"""One RANSAC run of MOP (paper App. A.3), batched and guided.

A :class:`Problem` describes what a hypothesis is fitted to: one or more *halves* (source,
destination) point sets that share the same minimal sample. Plain MOP has one half
``(x1 -> x2)``; MiHo has two, ``(x1 -> m)`` and ``(m -> x2)`` with ``m`` the midpoint
(App. B). A match is an inlier of a hypothesis iff, for every half, its two-way transfer error
is within the threshold and both projections keep the quasi-affine sign of the minimal sample
(App. A.3), i.e. the error below is the max over all halves and both directions.

Per run, hypotheses are drawn in batches (``FilterConfig.batch_size``, growing to 8x when
the stopping bound is far). For each batch: minimal-sample spread test (>= t_l in every
image), reflection check (MOP*, App. D), closed-form 4-point homographies with the sample's
quasi-affine signs (both ways, every half) from the same factors, then a one-way float32
error count on the pool, which bounds the full inlier count from above. Hypotheses are then
fully scored (two-way, every half, float64) in descending order of that bound until none
left can beat the best, so the best model is the one exhaustive scoring would pick; the
normalised-DLT singular-value test (> 0.05) runs just before full scoring, which rejects
exactly the hypotheses the paper rejects among those that can matter. Buffer candidates are
the two strongest of each batch with at least n possible inliers (the paper considers every
hypothesis; a weaker one could not enter a buffer of models worth bootstrapping). The run
stops at the adaptive bound for confidence ``p`` (never before ``min_iters``, never after
``max_iters``), counting every drawn sample as an iteration.

Sampling (``FilterConfig.sampling``): ``"uniform"`` is the paper's; ``"local"`` draws a seed
match uniformly and the other three among its ``local_neighbours`` nearest matches in the
joint ``(x1, x2)`` space (NAPSAC-style) for a ``local_fraction`` of the samples. The adaptive
bound then uses the all-inlier probability of that mixture (for local samples ``w * w_loc^3``
with ``w_loc`` the measured inlier fraction among the inliers' neighbours).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .config import FilterConfig
from .homography import (adjugate, dlt, dlt_singular_value, four_point, project,
                         triangle_orientations)

_PAIR_I = np.array([0, 0, 0, 1, 1, 2])
_PAIR_J = np.array([1, 2, 3, 2, 3, 3])


@dataclass(frozen=True)
class Problem:
    """Point sets of one filtering problem (all ``(N, 2)`` float64 pixels).

    Attributes:
        src, dst: per half, the source and destination points; a hypothesis holds one
            homography per half mapping ``src`` to ``dst``.
        spread: point sets in which the 4 sample points must be at least t_l apart.
        x1, x2: the two images' points (reflection check, local-sampling features).
    """

    src: tuple[np.ndarray, ...]
    dst: tuple[np.ndarray, ...]
    spread: tuple[np.ndarray, ...]
    x1: np.ndarray
    x2: np.ndarray
    # Stacked copies (N, halves or sets, 2) so that a batch needs one gather, not a loop.
    src_all: np.ndarray = field(init=False, repr=False)
    dst_all: np.ndarray = field(init=False, repr=False)
    spread_all: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "src_all", np.stack(self.src, axis=1))
        object.__setattr__(self, "dst_all", np.stack(self.dst, axis=1))
        object.__setattr__(self, "spread_all", np.stack(self.spread, axis=1))

    @property
    def num_halves(self) -> int:
        return len(self.src)


@dataclass
class Hypotheses:
    """A stack of ``K`` hypotheses: ``H`` and its adjugate ``Hinv`` ``(K, halves, 3, 3)``,
    quasi-affine reference signs ``sign``/``sign_inv`` ``(K, halves)`` and the minimal
    samples ``sample`` ``(K, 4)`` (global match indices)."""

    H: np.ndarray
    Hinv: np.ndarray
    sign: np.ndarray
    sign_inv: np.ndarray
    sample: np.ndarray

    def __len__(self) -> int:
        return self.H.shape[0]

    def take(self, idx) -> "Hypotheses":
        idx = np.atleast_1d(np.asarray(idx))
        return Hypotheses(self.H[idx], self.Hinv[idx], self.sign[idx], self.sign_inv[idx],
                          self.sample[idx])

    @staticmethod
    def concat(items: list["Hypotheses"]) -> "Hypotheses":
        items = [h for h in items if len(h)]
        if not items:
            return Hypotheses.empty(1)
        return Hypotheses(*(np.concatenate([getattr(h, f) for h in items]) for f in
                            ("H", "Hinv", "sign", "sign_inv", "sample")))

    @staticmethod
    def empty(halves: int) -> "Hypotheses":
        return Hypotheses(np.zeros((0, halves, 3, 3)), np.zeros((0, halves, 3, 3)),
                          np.zeros((0, halves)), np.zeros((0, halves)),
                          np.zeros((0, 4), dtype=np.int64))


def sample_signs(problem: Problem, H: np.ndarray, Hinv: np.ndarray, sample: np.ndarray):
    """Quasi-affine reference signs of minimal samples.

    Args:
        H, Hinv: ``(K, halves, 3, 3)`` hypotheses and their adjugates.
        sample: ``(K, 4)`` global match indices.

    Returns ``(ok, sign, sign_inv)``: ``ok`` ``(K,)`` whether the ``w`` of the 4 sample points
    share one nonzero sign in every half and both directions, and the signs ``(K, halves)``.
    """
    ok = np.ones(len(H), dtype=bool)
    signs = []
    for mat, pts in ((H, problem.src_all), (Hinv, problem.dst_all)):
        p = pts[sample]  # (K, 4, halves, 2)
        w = (mat[:, None, :, 2, :2] * p).sum(-1) + mat[:, None, :, 2, 2]  # (K, 4, halves)
        sg = np.sign(w)
        ok &= np.all(sg == sg[:, :1], axis=(1, 2)) & np.all(sg[:, 0] != 0, axis=1)
        signs.append(sg[:, 0])
    return ok, signs[0], signs[1]


def hypotheses_from_samples(problem: Problem, sample: np.ndarray, cfg: FilterConfig):
    """Fit and check hypotheses for minimal samples ``(B, 4)`` of global match indices.

    Applies the spread test, the reflection check (MOP*) and the quasi-affinity of the
    sample (both ways, every half); homographies come from the closed-form minimal solver.
    The singular-value test is separate (:func:`passes_singular_value_test`) so that it runs
    only on hypotheses that can matter; the result is the same as testing all of them first.
    Returns the surviving :class:`Hypotheses`.
    """
    p = problem.spread_all[sample]  # (B, 4, sets, 2)
    d = p[:, _PAIR_I] - p[:, _PAIR_J]  # (B, 6, sets, 2)
    ok = np.all((d * d).sum(-1) >= cfg.t_l**2, axis=(1, 2))
    if cfg.reflection_check and ok.any():
        o1 = triangle_orientations(problem.x1[sample])
        o2 = triangle_orientations(problem.x2[sample])
        ok &= np.all(o1 * o2 > 0, axis=1)
    sample = sample[ok]
    nh = problem.num_halves
    B = len(sample)
    if not B:
        return Hypotheses.empty(nh)
    src = problem.src_all[sample].transpose(0, 2, 1, 3).reshape(B * nh, 4, 2)
    dst = problem.dst_all[sample].transpose(0, 2, 1, 3).reshape(B * nh, 4, 2)
    H, s_fwd, s_inv = four_point(src, dst)
    H = H.reshape(B, nh, 3, 3)
    s_fwd = s_fwd.reshape(B, nh, 4)
    s_inv = s_inv.reshape(B, nh, 4)
    # Quasi-affinity of the sample: one nonzero sign of w per half and direction.
    ok = np.all(np.isfinite(H), axis=(1, 2, 3))
    for sg in (s_fwd, s_inv):
        ok &= np.all(sg == sg[:, :, :1], axis=(1, 2)) & np.all(sg[:, :, 0] != 0, axis=1)
    H = H[ok]
    return Hypotheses(H, adjugate(H), s_fwd[ok, :, 0], s_inv[ok, :, 0], sample[ok])


def passes_singular_value_test(problem: Problem, hyp: Hypotheses, cfg: FilterConfig) -> np.ndarray:
    """``(K,)`` bool: the normalised minimal DLT system of every half has its smallest
    singular value above ``cfg.min_singular_value`` (paper App. A.3)."""
    K, nh = len(hyp), problem.num_halves
    src = problem.src_all[hyp.sample].transpose(0, 2, 1, 3).reshape(K * nh, 4, 2)
    dst = problem.dst_all[hyp.sample].transpose(0, 2, 1, 3).reshape(K * nh, 4, 2)
    sv = dlt_singular_value(src, dst).reshape(K, nh)
    return np.all(sv > cfg.min_singular_value, axis=1)


def error_sq(problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> np.ndarray:
    """Squared MOP error ``(K, n)`` of hypotheses on the matches ``idx`` ``(n,)``: the max over
    halves and directions of the squared transfer error; ``inf`` where a projection breaks
    the quasi-affine sign of the hypothesis' sample."""
    err = np.zeros((len(hyp), len(idx)))
    for h in range(problem.num_halves):
        src, dst = problem.src[h][idx], problem.dst[h][idx]
        for mat, sgn, a, b in ((hyp.H, hyp.sign, src, dst), (hyp.Hinv, hyp.sign_inv, dst, src)):
            x, y, w = project(mat[:, h], a)
            e = (x - b[:, 0]) ** 2 + (y - b[:, 1]) ** 2
            e[np.sign(w) != sgn[:, h, None]] = np.inf
            np.maximum(err, e, out=err)
    return err


def one_way_count(problem: Problem, hyp: Hypotheses, idx: np.ndarray, t2: float,
                  block: int = 131072) -> np.ndarray:
    """Inliers ``(K,)`` under the first half's forward error only: an upper bound of the
    full inlier count (the full error is a max that includes this term).

    Division-free and in float32 (``|u - x w|^2 <= t^2 w^2`` with ``w`` of the sample's
    sign), by broadcasting over blocks of hypotheses sized to stay in cache (measured
    3x faster than a GEMM with inner dimension 3 here). float32 rounding moves the bound by
    about 1e-4 px at 1000 px coordinates.
    """
    src = problem.src[0][idx].astype(np.float32)
    dst = problem.dst[0][idx].astype(np.float32)
    X, Y, x2, y2 = src[:, 0], src[:, 1], dst[:, 0], dst[:, 1]
    n = len(idx)
    K = len(hyp)
    # Sign-normalised so that the quasi-affine test is simply w > 0.
    Hs = (hyp.H[:, 0] * hyp.sign[:, 0, None, None]).astype(np.float32).reshape(K, 9, 1)
    counts = np.empty(K, dtype=np.int64)
    kb = max(1, block // max(n, 1))
    for a in range(0, K, kb):
        h = Hs[a:a + kb]
        W = h[:, 6] * X
        W += h[:, 7] * Y
        W += h[:, 8]
        U = h[:, 0] * X
        U += h[:, 1] * Y
        U += h[:, 2]
        U -= W * x2
        V = h[:, 3] * X
        V += h[:, 4] * Y
        V += h[:, 5]
        V -= W * y2
        U *= U
        V *= V
        U += V
        ok = W > 0
        W *= W
        W *= t2
        ok &= U <= W
        counts[a:a + kb] = np.count_nonzero(ok, axis=1)
    return counts


@dataclass
class RoundResult:
    """Best model of one RANSAC run: ``hyp`` (1 hypothesis), ``err2`` ``(n_pool,)`` its
    squared errors on the pool, ``count`` its t_l inliers, and counters."""

    hyp: Hypotheses
    err2: np.ndarray
    count: int
    stats: dict = field(default_factory=dict)


def _required_iters(w: float, w_loc: float, local_fraction: float, p: float) -> float:
    p_all = local_fraction * w * w_loc**3 + (1.0 - local_fraction) * w**4
    if p_all <= 0:
        return math.inf
    if p_all >= 1:
        return 0.0
    return math.log(1.0 - p) / math.log1p(-p_all)


def _greedy_buffer(cands: list[tuple[Hypotheses, np.ndarray]], best_mask: np.ndarray, z: int):
    """Top-z sub-optimal models ordered by inliers not covered by the best and the better
    buffered ones (paper App. A.3, ``v_i >= v_{i+1}``)."""
    if z == 0 or not cands:
        return []
    covered = best_mask.copy()
    masks = np.stack([m for _, m in cands])
    chosen = []
    free = np.ones(len(cands), dtype=bool)
    for _ in range(min(z, len(cands))):
        gain = np.where(free, (masks & ~covered).sum(1), -1)
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(cands[k][0])
        covered |= masks[k]
        free[k] = False
    return chosen


def ransac_round(problem: Problem, pool: np.ndarray, cfg: FilterConfig, rng: np.random.Generator,
                 buffer: list[Hypotheses]) -> tuple[RoundResult | None, list[Hypotheses]]:
    """Run one RANSAC search on the matches ``pool`` (``(n,)`` global indices).

    Args:
        buffer: the global top-z buffer of sub-optimal hypotheses; evaluated first
            (bootstrap) and returned updated.

    Returns:
        ``(result, buffer)``; ``result`` is ``None`` when no valid hypothesis was found.
    """
    n = len(pool)
    stats = {"drawn": 0, "valid": 0, "full_scored": 0}
    if n < 4:
        return None, buffer
    t2 = cfg.t_l**2
    best_hyp, best_err, best_count, best_mask = None, None, -1, None
    cands: list[tuple[Hypotheses, np.ndarray]] = []

    def consider(hyp: Hypotheses, err: np.ndarray) -> bool:
        nonlocal best_hyp, best_err, best_count, best_mask
        masks = err <= t2
        counts = masks.sum(1)
        improved = False
        for k in np.argsort(-counts, kind="stable"):
            if counts[k] > best_count:
                if best_hyp is not None:
                    cands.append((best_hyp, best_mask))
                best_hyp, best_err = hyp.take(k), err[k]
                best_count, best_mask = int(counts[k]), masks[k]
                improved = True
            elif counts[k] > 0:
                cands.append((hyp.take(k), masks[k]))
        return improved

    if buffer:
        boot = Hypotheses.concat(buffer)
        consider(boot, error_sq(problem, boot, pool))
        stats["full_scored"] += len(boot)

    use_local = cfg.sampling == "local" and n > cfg.local_neighbours + 1
    f_local = cfg.local_fraction if use_local else 0.0
    tree = feats = None
    if use_local:
        from scipy.spatial import cKDTree

        feats = np.concatenate([problem.x1[pool], problem.x2[pool]], axis=1)
        tree = cKDTree(feats)  # building is cheap; neighbours are queried only where needed

    nb_cache = np.empty((n, cfg.local_neighbours), dtype=np.int64)
    nb_known = np.zeros(n, dtype=bool)

    def neighbours(pos: np.ndarray) -> np.ndarray:
        """``(len(pos), k)`` pool positions of the k nearest matches of pool positions ``pos``
        (queried once per position, on demand)."""
        todo = np.unique(pos[~nb_known[pos]])
        if len(todo):
            nb_cache[todo] = tree.query(feats[todo], k=cfg.local_neighbours + 1)[1][:, 1:]
            nb_known[todo] = True
        return nb_cache[pos]

    def local_inlier_fraction() -> float:
        if tree is None or best_mask is None or best_count <= 0:
            return 0.0
        inl = np.flatnonzero(best_mask)
        probe = inl[np.linspace(0, len(inl) - 1, min(len(inl), 256)).astype(np.int64)]
        return float(best_mask[neighbours(probe)].mean())

    def update_required() -> float:
        if best_count <= 0:
            return float(cfg.max_iters)
        return _required_iters(best_count / n, local_inlier_fraction(), f_local, cfg.confidence)

    required = update_required()
    while stats["drawn"] < (target := max(cfg.min_iters, min(required, cfg.max_iters))):
        # Small batches while the bound may still drop, bigger ones when it will not.
        B = cfg.batch_size
        if best_count > 0:
            B = int(min(max(B, target - stats["drawn"]), 8 * B))
        seeds = rng.integers(0, n, B)
        others = rng.integers(0, n, (B, 3))
        if use_local:
            is_local = np.flatnonzero(rng.random(B) < f_local)
            pick = rng.integers(0, cfg.local_neighbours, (len(is_local), 3))
            if len(is_local):
                nb = neighbours(seeds[is_local])
                others[is_local] = np.take_along_axis(nb, pick, axis=1)
        sample = pool[np.concatenate([seeds[:, None], others], axis=1)]
        stats["drawn"] += B
        hyp = hypotheses_from_samples(problem, sample, cfg)
        stats["valid"] += len(hyp)
        if not len(hyp):
            continue
        ub = one_way_count(problem, hyp, pool, t2)
        order = np.argsort(-ub, kind="stable")
        ub = ub[order]
        improved = False
        # Buffer candidates: the batch's two strongest (a model below n inliers is never
        # kept, so weaker ones are not worth a full score).
        n_buf = int(np.count_nonzero(ub[: min(2, cfg.buffer_size)] >= cfg.inlier_count))
        start = 0
        # Exact search for a new best: full-score in descending upper-bound order, in small
        # groups, until no remaining upper bound can beat the best count.
        while start < len(order) and (ub[start] > best_count or start < n_buf):
            stop = start + 4
            sub = hyp.take(order[start:stop][ub[start:stop] > 0])
            start = stop
            sub = sub.take(np.flatnonzero(passes_singular_value_test(problem, sub, cfg)))
            if not len(sub):
                continue
            stats["full_scored"] += len(sub)
            improved |= consider(sub, error_sq(problem, sub, pool))
        if improved:
            required = update_required()

    if best_hyp is None:
        return None, buffer

    for _ in range(cfg.refit_iters):
        refit = _refit(problem, best_hyp, pool[best_err <= t2])
        if refit is None:
            break
        err = error_sq(problem, refit, pool)[0]
        count = int((err <= t2).sum())
        stats["full_scored"] += 1
        if count < best_count:
            break
        unchanged = count == best_count and np.array_equal(err <= t2, best_mask)
        best_hyp, best_err, best_count, best_mask = refit, err, count, err <= t2
        if unchanged:
            break

    buffer = _greedy_buffer(cands, best_mask, cfg.buffer_size)
    stats["required_iters"] = required
    return RoundResult(best_hyp, best_err, best_count, stats), buffer


def _refit(problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> Hypotheses | None:
    """Least-squares normalised DLT of every half on the matches ``idx`` (global indices);
    ``None`` when degenerate or when the sample loses its quasi-affine consistency."""
    if len(idx) < 5:
        return None
    nh = problem.num_halves
    H = np.empty((1, nh, 3, 3))
    for h in range(nh):
        H[:, h], _ = dlt(problem.src[h][idx][None], problem.dst[h][idx][None])
    if not np.all(np.isfinite(H)):
        return None
    Hinv = adjugate(H)
    ok, sign, sign_inv = sample_signs(problem, H, Hinv, hyp.sample)
    if not ok[0]:
        return None
    return Hypotheses(H, Hinv, sign, sign_inv, hyp.sample.copy())
