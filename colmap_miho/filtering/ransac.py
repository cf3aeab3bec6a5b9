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
``max_iters``). Iterations are the samples that pass the spread test: a draw that fails it
is not a hypothesis, so it counts neither towards c_min / c_max nor against the bound
(samples that the reflection or quasi-affinity checks reject do count). At most
``10 x max_iters`` samples are drawn, for pools where almost nothing is spread out.

Sampling (``FilterConfig.sampling``): ``"uniform"`` is the paper's; ``"local"`` draws a seed
match uniformly and the other three among its ``local_neighbours`` nearest matches in the
joint ``(x1, x2)`` space (NAPSAC-style) that lie at least t_l from the seed and from each
other in every spread set, for a ``local_fraction`` of the samples. Plain nearest
neighbours are mostly closer than t_l to each other (measured: 79-95% of such samples failed
the spread test on SIFT pairs; 2-7% fail now). The adaptive bound uses the all-inlier
probability of that mixture (for local samples ``w * w_loc^3`` with ``w_loc`` the measured
inlier fraction among the inliers' neighbours).

Where the heavy kernels run (minimal solver, bounds, singular-value test, full scoring):
:class:`NumpyScoring` (numpy, the default) or its torch twin
:class:`~colmap_miho.filtering.torch_scoring.TorchScoring` (any torch device), passed as
``scoring``; sampling and the search's bookkeeping are numpy for both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .config import FilterConfig

if TYPE_CHECKING:
    from scipy.spatial import cKDTree
from .homography import (
    adjugate,
    array_module,
    dlt,
    dlt_singular_value,
    four_point,
    one_way_inside,
    transfer_error_sq,
    triangle_orientations,
)

_DRAW_CAP = 10  # most draws per RANSAC run, in units of c_max
_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))  # the 6 point pairs of a sample


def _apart_sets(dx: np.ndarray, dy: np.ndarray, t2: float) -> np.ndarray:
    """``(...)`` bool from the differences' x and y ``(sets, ...)``: the squared distance
    ``dx * dx + dy * dy`` (the bits a ``sum`` over (x, y) gives) is at least ``t2`` in every
    set. Written out over the tiny sets axis (numpy reductions over axes of length 2-3 cost
    far more than the arithmetic); overwrites ``dx`` and ``dy``."""
    dx *= dx
    dy *= dy
    dx += dy
    ok = dx[0] >= t2
    for k in range(1, dx.shape[0]):
        ok &= dx[k] >= t2
    return ok


@dataclass(frozen=True)
class Problem:
    """Point sets of one filtering problem (all ``(N, 2)`` float64 pixels: numpy arrays, or
    torch tensors for the device copy of :class:`~colmap_miho.filtering.torch_scoring.TorchScoring`).

    Attributes:
        src, dst: per half, the source and destination points; a hypothesis holds one
            homography per half mapping ``src`` to ``dst``.
        spread: point sets in which the 4 sample points must be at least t_l apart.
        x1, x2: the two images' points (reflection check, local-sampling features).
        error_scale: factor applied to every transfer error before the thresholds (1 for
            MOP; 2 for MiHo with thresholds on the full match, see
            ``FilterConfig.miho_threshold``).
    """

    src: tuple[np.ndarray, ...]
    dst: tuple[np.ndarray, ...]
    spread: tuple[np.ndarray, ...]
    x1: np.ndarray
    x2: np.ndarray
    error_scale: float = 1.0
    # Stacked copies (N, halves or sets, 2) so that a batch needs one gather, not a loop.
    src_all: np.ndarray = field(init=False, repr=False)
    dst_all: np.ndarray = field(init=False, repr=False)
    spread_all: np.ndarray = field(init=False, repr=False)
    # The spread sets by coordinate, (2, sets, N) (numpy only, None for torch): a gather
    # along the last axis (np.take) costs several times less than one of 2-6 float rows.
    spread_xy: np.ndarray | None = field(init=False, repr=False)

    def __post_init__(self) -> None:
        xp = array_module(self.x1)
        object.__setattr__(self, "src_all", xp.stack(self.src, axis=1))
        object.__setattr__(self, "dst_all", xp.stack(self.dst, axis=1))
        object.__setattr__(self, "spread_all", xp.stack(self.spread, axis=1))
        object.__setattr__(self, "spread_xy", np.ascontiguousarray(
            self.spread_all.transpose(2, 1, 0)) if xp is np else None)

    @property
    def num_halves(self) -> int:
        return len(self.src)


@dataclass
class Hypotheses:
    """A stack of ``K`` hypotheses: ``H`` and its adjugate ``Hinv`` ``(K, halves, 3, 3)``,
    quasi-affine reference signs ``sign``/``sign_inv`` ``(K, halves)`` and the minimal
    samples ``sample`` ``(K, 4)`` (global match indices), numpy arrays."""

    H: np.ndarray
    Hinv: np.ndarray
    sign: np.ndarray
    sign_inv: np.ndarray
    sample: np.ndarray

    def __len__(self) -> int:
        return self.H.shape[0]

    def take(self, idx) -> Hypotheses:
        idx = np.atleast_1d(np.asarray(idx))
        return Hypotheses(self.H[idx], self.Hinv[idx], self.sign[idx], self.sign_inv[idx],
                          self.sample[idx])

    @staticmethod
    def concat(items: list[Hypotheses]) -> Hypotheses:
        items = [h for h in items if len(h)]
        if not items:
            return Hypotheses.empty(1)
        return Hypotheses(*(np.concatenate([getattr(h, f) for h in items]) for f in
                            ("H", "Hinv", "sign", "sign_inv", "sample")))

    @staticmethod
    def empty(halves: int) -> Hypotheses:
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


def spread_ok(problem: Problem, sample: np.ndarray, t_l: float) -> np.ndarray:
    """``(B,)`` bool: the 4 points of each minimal sample ``(B, 4)`` are pairwise at least
    ``t_l`` pixels apart in every spread set (paper App. A.3)."""
    assert problem.spread_xy is not None, "sampling runs on the numpy problem"
    px, py = np.take(problem.spread_xy, sample.T, axis=2)  # (sets, 4, B) each
    ok = np.ones(len(sample), dtype=bool)
    for i, j in _PAIRS:
        ok &= _apart_sets(px[:, i] - px[:, j], py[:, i] - py[:, j], t_l**2)
    return ok


def checked_samples(problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                    ok: np.ndarray | None = None) -> np.ndarray:
    """The minimal samples ``(B, 4)`` that pass the spread test (unless its result ``ok``
    ``(B,)`` is given) and, for MOP*, the reflection check (App. D)."""
    ok = spread_ok(problem, sample, cfg.t_l) if ok is None else ok.copy()
    if cfg.reflection_check and ok.any():
        o1 = triangle_orientations(problem.x1[sample])
        o2 = triangle_orientations(problem.x2[sample])
        ok &= np.all(o1 * o2 > 0, axis=1)
    return sample[ok]


def _per_half(pts_all: np.ndarray, sample: np.ndarray) -> np.ndarray:
    """``(B * halves, 4, 2)`` sample points, half by half, from ``pts_all`` ``(N, halves, 2)``
    and samples ``(B, 4)``: ``pts_all[sample]`` with the halves moved ahead of the 4 points
    (gathered as whole rows by ``np.take``, faster than fancy indexing; the same values)."""
    N, nh, _ = pts_all.shape
    B = len(sample)
    rows = np.take(pts_all.reshape(N, nh * 2), sample, axis=0)  # (B, 4, halves * 2)
    return rows.reshape(B, 4, nh, 2).transpose(0, 2, 1, 3).reshape(B * nh, 4, 2)


def _one_sign(sg: np.ndarray) -> np.ndarray:
    """``(B,)`` bool from signs ``sg`` ``(B, halves, 4)`` in {-1, 0, 1}: in every half the 4
    signs are one nonzero sign (the products with the first are all 1)."""
    ok = sg[:, :, 0] * sg[:, :, 1] > 0
    ok &= sg[:, :, 0] * sg[:, :, 2] > 0
    ok &= sg[:, :, 0] * sg[:, :, 3] > 0
    return ok.all(axis=1)


def hypotheses_from_samples(problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                            ok: np.ndarray | None = None):
    """Fit and check hypotheses for minimal samples ``(B, 4)`` of global match indices.

    Applies the spread test (unless its result ``ok`` ``(B,)`` is given), the reflection
    check (MOP*) and the quasi-affinity of the sample (both ways, every half); homographies
    come from the closed-form minimal solver. The singular-value test is separate
    (:func:`passes_singular_value_test`) so that it runs only on hypotheses that can matter;
    the result is the same as testing all of them first. Returns the surviving
    :class:`Hypotheses`.
    """
    sample = checked_samples(problem, sample, cfg, ok)
    nh = problem.num_halves
    B = len(sample)
    if not B:
        return Hypotheses.empty(nh)
    src = _per_half(problem.src_all, sample)
    dst = _per_half(problem.dst_all, sample)
    H, s_fwd, s_inv = four_point(src, dst)
    H = H.reshape(B, nh, 3, 3)
    s_fwd = s_fwd.reshape(B, nh, 4)
    s_inv = s_inv.reshape(B, nh, 4)
    # Quasi-affinity of the sample: one nonzero sign of w per half and direction.
    ok = np.isfinite(H.reshape(B, -1)).all(axis=1)
    ok &= _one_sign(s_fwd.reshape(B, -1, 4)) & _one_sign(s_inv.reshape(B, -1, 4))
    H = H[ok]
    return Hypotheses(H, adjugate(H), s_fwd[ok, :, 0], s_inv[ok, :, 0], sample[ok])


def passes_singular_value_test(problem: Problem, hyp: Hypotheses, cfg: FilterConfig) -> np.ndarray:
    """``(K,)`` bool: the normalised minimal DLT system of every half has its smallest
    singular value above ``cfg.min_singular_value`` (paper App. A.3)."""
    K, nh = len(hyp), problem.num_halves
    src = _per_half(problem.src_all, hyp.sample)
    dst = _per_half(problem.dst_all, hyp.sample)
    sv = dlt_singular_value(src, dst).reshape(K, nh)
    return np.all(sv > cfg.min_singular_value, axis=1)


def error_sq(problem: Problem, hyp: Hypotheses, idx: np.ndarray,
             scratch: _Scratch | None = None) -> np.ndarray:
    """Squared MOP error ``(K, n)`` of hypotheses on the matches ``idx`` ``(n,)``: the max over
    halves and directions of the squared transfer error (times ``problem.error_scale``
    squared); ``inf`` where a projection breaks the quasi-affine sign of the hypothesis'
    sample. The torch path computes the same per-element formula stacked over halves and
    directions (``TorchScoring._error_sq``)."""
    err = None
    # (2, n) coordinates per half (kept in ``scratch`` for the next call on the same pool)
    points = (_Scratch() if scratch is None else scratch).points(problem, idx)
    # w == 0 gives inf / nan errors; those entries break the quasi-affine sign and are set
    # to inf below, after the max, exactly as if they had been set before it.
    with np.errstate(divide="ignore", invalid="ignore"):
        for h, (src, dst) in enumerate(points):
            for mat, sgn, a, b in ((hyp.H, hyp.sign, src, dst),
                                   (hyp.Hinv, hyp.sign_inv, dst, src)):
                e, w = transfer_error_sq(mat[:, h], a.T, b.T)  # (n, 2) views
                if err is None:
                    err = e  # the max of 0 and e >= 0
                else:
                    np.maximum(err, e, out=err)
                # sign(w) != sign of the sample <=> w * sign <= 0: the sign is +-1 and w is
                # finite (finite homography and points).
                w *= sgn[:, h, None]
                np.copyto(err, np.inf, where=w <= 0)
    assert err is not None  # a problem has at least one half
    if problem.error_scale != 1.0:
        err *= problem.error_scale**2
    return err


class _Scratch:
    """Work arrays reused from call to call, by name: a fresh numpy array above malloc's mmap
    threshold (~128 KiB) can pay its page faults on every call (measured in isolation: the
    one-way kernel on 65 x 2000 2.5x, a 32-hypothesis transfer error 3x faster reused).
    Not for sharing between threads (one filter call's scoring runs in one thread)."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}
        self._points_of: tuple[Problem, np.ndarray] | None = None
        self._points: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
        self._points32: tuple[np.ndarray, np.ndarray] | None = None

    def points(self, problem: Problem, idx: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """Per half, ``(src, dst)`` of the matches ``idx`` as ``(2, n)`` arrays (x row, y row,
        each contiguous), kept while the same ``problem`` and ``idx`` objects come back (a
        RANSAC run scores on one pool array, never changed in place)."""
        key = self._points_of
        if key is None or key[0] is not problem or key[1] is not idx:
            self._points = tuple((problem.src[h][idx].T.copy(), problem.dst[h][idx].T.copy())
                                 for h in range(problem.num_halves))
            self._points32 = None
            self._points_of = (problem, idx)
        return self._points

    def points32(self, problem: Problem, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first half's ``(src, dst)`` of :meth:`points` in float32."""
        pts = self.points(problem, idx)
        if self._points32 is None:
            self._points32 = (pts[0][0].astype(np.float32), pts[0][1].astype(np.float32))
        return self._points32

    def get(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        """A C-contiguous array of ``shape`` and ``dtype`` (contents undefined)."""
        size = math.prod(shape)
        a = self._arrays.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            a = self._arrays[name] = np.empty(size, dtype=dtype)
        return a[:size].reshape(shape)


def inlier_masks(problem: Problem, hyp: Hypotheses, idx: np.ndarray, t2: float,
                 scratch: _Scratch | None = None) -> np.ndarray:
    """``(K, n)`` bool: ``error_sq(problem, hyp, idx) <= t2``, the same decisions bit for bit,
    computed term by term (halves and directions): after each term only the matches that
    some hypothesis still keeps are carried on.

    The same because the error is a max of terms scaled by ``error_scale**2`` (a rounded
    product is monotone, so ``max(a, b) s <= t2`` iff ``a s <= t2`` and ``b s <= t2``; for a
    power of two ``a s <= t2`` iff ``a <= t2 / s``, both exact) and an entry whose projection
    breaks the sample's sign is inf, i.e. outside. Each homography is first multiplied by
    its sample's sign (+-1): that negates ``w`` and the projected numerators exactly, so the
    error keeps its bits and the sign test becomes ``w > 0``.
    """
    K, n = len(hyp), len(idx)
    s2 = problem.error_scale**2
    scratch = _Scratch() if scratch is None else scratch
    if math.frexp(s2)[0] == 0.5:  # a power of two: scale the threshold instead
        t2, s2 = t2 / s2, 1.0
    ok: np.ndarray | None = None
    cols: np.ndarray | None = None  # the matches still carried (None: all)
    terms = 2 * problem.num_halves
    with np.errstate(divide="ignore", invalid="ignore"):  # w == 0: rejected by the sign
        for h, (src, dst) in enumerate(scratch.points(problem, idx)):  # (2, n) each
            for mat, sgn, a, b in ((hyp.H, hyp.sign, src, dst),
                                   (hyp.Hinv, hyp.sign_inv, dst, src)):
                terms -= 1
                if cols is not None:
                    a, b = a[:, cols], b[:, cols]
                shape = (K, a.shape[1])
                work = tuple(scratch.get("ewyt", (4,) + shape, np.float64))  # 4 (K, n)
                # (n, 2) views with contiguous x and y: the same values, read faster
                e, w = transfer_error_sq(mat[:, h] * sgn[:, h, None, None], a.T, b.T, work)
                if s2 != 1.0:
                    e *= s2
                inside = e <= t2
                inside &= w > 0  # the sample's sign (w is finite)
                if ok is None:
                    ok = inside
                else:
                    ok &= inside
                if not terms:  # the last term: nothing left to carry
                    break
                alive = np.flatnonzero(ok.any(axis=0))
                if 4 * len(alive) < 3 * ok.shape[1]:
                    ok = ok[:, alive]
                    cols = alive if cols is None else cols[alive]
    assert ok is not None  # a problem has at least one half
    if cols is None:
        return ok
    mask = np.zeros((K, n), dtype=bool)
    mask[:, cols] = ok
    return mask


def one_way_count(problem: Problem, hyp: Hypotheses, idx: np.ndarray, t2: float,
                  block: int = 131072, scratch: _Scratch | None = None) -> np.ndarray:
    """Inliers ``(K,)`` under the first half's forward error only: an upper bound of the
    full inlier count (the full error is a max that includes this term).

    Division-free and in float32 (``|u - x w|^2 <= t^2 w^2`` with ``w`` of the sample's
    sign), by broadcasting over blocks of hypotheses sized to stay in cache (measured
    3x faster than a GEMM with inner dimension 3 here). float32 rounding moves the bound by
    about 1e-4 px at 1000 px coordinates.
    """
    t2 = t2 / problem.error_scale**2
    scratch = _Scratch() if scratch is None else scratch
    src, dst = scratch.points32(problem, idx)  # (2, n) float32 each
    X, Y, x2, y2 = src[0], src[1], dst[0], dst[1]
    n = len(idx)
    K = len(hyp)
    # Sign-normalised so that the quasi-affine test is simply w > 0.
    Hs = (hyp.H[:, 0] * hyp.sign[:, 0, None, None]).astype(np.float32).reshape(K, 9, 1)
    counts = np.empty(K, dtype=np.int64)
    kb = max(1, block // max(n, 1))
    for a in range(0, K, kb):
        shape = (min(kb, K - a), n)
        out = tuple(scratch.get("WUVT", (4,) + shape, np.float32)) + tuple(
            scratch.get("ok,tmp", (2,) + shape, np.bool_))
        ok = one_way_inside(Hs[a:a + kb], X, Y, x2, y2, t2, out)
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


def _greedy_buffer(cands: list[tuple[Hypotheses, int, np.ndarray]], best_mask: np.ndarray,
                   z: int):
    """Top-z sub-optimal models ordered by inliers not covered by the best and the better
    buffered ones (paper App. A.3, ``v_i >= v_{i+1}``); ``cands`` as in :class:`_Search`."""
    if z == 0 or not cands:
        return []
    covered = best_mask.copy()
    masks = np.stack([m for _, _, m in cands])
    chosen = []
    free = np.ones(len(cands), dtype=bool)
    for _ in range(min(z, len(cands))):
        gain = np.where(free, np.count_nonzero(masks & ~covered, axis=1), -1)
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(cands[k][0].take(cands[k][1]))
        covered |= masks[k]
        free[k] = False
    return chosen


@dataclass
class _Search:
    """State of one RANSAC run: the best model so far (``hyp``; ``err`` its squared errors on
    the pool, ``mask`` its t_l inliers, ``count`` their number, -1 before any model) and the
    sub-optimal candidates for the top-z buffer, ``(hypotheses, row, inlier mask)`` (the
    candidate is row ``row`` of ``hypotheses``: taken out only if the buffer chooses it)."""

    t2: float
    hyp: Hypotheses | None = None
    err: np.ndarray | None = None
    count: int = -1
    mask: np.ndarray | None = None
    cands: list[tuple[Hypotheses, int, np.ndarray]] = field(default_factory=list)

    def consider(self, hyp: Hypotheses, masks: np.ndarray, err: np.ndarray | None = None) -> bool:
        """Take fully scored hypotheses: their t_l inlier ``masks`` ``(K, n_pool)`` and, when
        at hand, their squared errors ``err`` (otherwise the best's are computed at the end
        of the run); returns whether the best model changed. A replaced best and every other
        model with inliers become candidates."""
        counts = np.count_nonzero(masks, axis=1)
        improved = False
        for k in np.argsort(-counts, kind="stable"):
            if counts[k] > self.count:
                if self.hyp is not None and self.mask is not None:  # set together
                    self.cands.append((self.hyp, 0, self.mask))
                self.hyp, self.err = hyp.take(k), None if err is None else err[k]
                self.count, self.mask = int(counts[k]), masks[k]
                improved = True
            elif counts[k] > 0:
                self.cands.append((hyp, int(k), masks[k]))
        return improved


class LocalCandidates:
    """Candidate neighbours of local sampling for one filtering problem, shared by its MOP
    rounds: for each match, its ``4 k`` nearest matches in the joint ``(x1, x2)`` space
    (``k = local_neighbours``) and whether each lies at least t_l from it in every spread
    set. Both are independent of the pool, so they are computed once per match."""

    SEARCH = 4

    def __init__(self, problem: Problem, cfg: FilterConfig) -> None:
        from scipy.spatial import cKDTree

        n = len(problem.x1)
        assert problem.spread_xy is not None, "local sampling runs on the numpy problem"
        self._sx, self._sy = problem.spread_xy  # (sets, N) each
        self._t2 = cfg.t_l**2
        self.feats = np.concatenate([problem.x1, problem.x2], axis=1)
        self._tree = cKDTree(self.feats)
        self._q = max(min(n, self.SEARCH * cfg.local_neighbours + 1) - 1, 0)
        self._cand = np.full((n, self._q), -1, dtype=np.int64)
        self._far = np.zeros((n, self._q), dtype=bool)
        self._known = np.zeros(n, dtype=bool)

    def far(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Whether matches ``a`` and ``b`` (broadcast) are >= t_l apart in every spread set."""
        sx, sy = self._sx, self._sy
        return _apart_sets(np.take(sx, a, axis=1) - np.take(sx, b, axis=1),
                           np.take(sy, a, axis=1) - np.take(sy, b, axis=1), self._t2)

    def get(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(cand, far)``, each ``(len(idx), 4k)``: the nearest matches of matches ``idx``
        (nearest first) and whether each is far enough for the spread test. Matches are
        searched when first asked for (one tree query per call for the missing ones; a
        match's neighbours do not depend on what it is queried with: measured, local
        sampling asks for 40-100% of the matches, 86% on average, over ~17 calls)."""
        todo = idx[~self._known[idx]]
        if len(todo):
            todo = np.unique(todo)
        if len(todo) and self._q:
            cand = self._tree.query(self.feats[todo], k=self._q + 1)[1][:, 1:]
            self._cand[todo] = cand
            self._far[todo] = self.far(cand, todo[:, None])
        self._known[todo] = True
        return self._cand[idx], self._far[idx]


class _Sampler:
    """Minimal samples over the pool: uniform, or a ``local_fraction`` of them drawn around
    a seed match among its ``local_neighbours`` nearest pool matches in ``(x1, x2)`` space.

    Local samples are drawn so that they pass the spread test: a seed's neighbours are the
    nearest of its :class:`LocalCandidates` that are still in the pool and lie at least t_l
    from it in every spread set (image 1, image 2 and, for MiHo, the midpoints; where fewer
    than k of them are left in the pool, the nearest in the pool are searched anew), and the
    three others are drawn one by one among the neighbours at least t_l from those already
    drawn. A seed without three such neighbours gives a sample that fails the spread test.
    Neighbour lists are computed once per pool position, on demand.
    """

    def __init__(self, problem: Problem, pool: np.ndarray, cfg: FilterConfig,
                 candidates: LocalCandidates | None = None) -> None:
        n = len(pool)
        self.pool = pool
        self.k = cfg.local_neighbours
        self.local = cfg.sampling == "local" and n > cfg.local_neighbours + 1
        self.fraction = cfg.local_fraction if self.local else 0.0
        self._cands: LocalCandidates | None = None
        if self.local:
            self._cands = candidates if candidates is not None else LocalCandidates(problem, cfg)
            self._pos = np.full(len(problem.x1), -1, dtype=np.int64)  # global -> pool position
            self._pos[pool] = np.arange(n)
        self._pool_tree: cKDTree | None = None
        self._nb = np.full((n, self.k), -1, dtype=np.int64)  # -1 = no such neighbour
        # (sets, n) x and y of the spread sets of the pool, for the local draws
        self._spread_x: np.ndarray | None = None
        self._spread_y: np.ndarray | None = None
        if self.local:
            assert problem.spread_xy is not None, "local sampling runs on the numpy problem"
            self._spread_x, self._spread_y = np.take(problem.spread_xy, pool, axis=2)
        self._t2 = cfg.t_l**2
        self._known = np.zeros(n, dtype=bool)

    def neighbours(self, pos: np.ndarray) -> np.ndarray:
        """``(len(pos), k)`` pool positions of the nearest pool matches at least t_l from each
        of the pool positions ``pos`` in every spread set (-1 where there are fewer than k)."""
        todo = np.unique(pos[~self._known[pos]])
        if len(todo):
            assert self._cands is not None, "neighbours are searched with local sampling only"
            cand, far = self._cands.get(self.pool[todo])
            cand_pos = np.where(cand >= 0, self._pos[np.maximum(cand, 0)], -1)
            nb = self._first_k(cand_pos, far & (cand_pos >= 0))
            # Where earlier rounds removed too many of the candidates, search the pool itself.
            short = np.flatnonzero((nb < 0).any(axis=1))
            if len(short):
                nb[short] = self._first_k(*self._pool_candidates(todo[short]))
            self._nb[todo] = nb
            self._known[todo] = True
        return self._nb[pos]

    def _first_k(self, cand: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """The first k candidates (pool positions, nearest first) where ``ok``, -1 padded."""
        order = np.argsort(~ok, axis=1, kind="stable")[:, : self.k]
        nb = np.take_along_axis(cand, order, axis=1)
        nb[~np.take_along_axis(ok, order, axis=1)] = -1
        if nb.shape[1] < self.k:
            nb = np.pad(nb, ((0, 0), (0, self.k - nb.shape[1])), constant_values=-1)
        return nb

    def _pool_candidates(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest pool matches of pool positions ``pos`` (as pool positions) and whether
        each is far enough for the spread test, from a k-d tree over the pool."""
        cands = self._cands
        assert cands is not None, "neighbours are searched with local sampling only"
        if self._pool_tree is None:
            from scipy.spatial import cKDTree

            self._pool_tree = cKDTree(cands.feats[self.pool])
        q = min(len(self.pool), LocalCandidates.SEARCH * self.k + 1)
        cand = self._pool_tree.query(cands.feats[self.pool[pos]], k=q)[1][:, 1:]
        return cand, cands.far(self.pool[cand], self.pool[pos][:, None])

    def local_inlier_fraction(self, search: _Search) -> float:
        """Share of the best model's inliers among the neighbours of (up to 256) of them."""
        if self._cands is None or search.mask is None or search.count <= 0:
            return 0.0
        inl = np.flatnonzero(search.mask)
        probe = inl[np.linspace(0, len(inl) - 1, min(len(inl), 256)).astype(np.int64)]
        nb = self.neighbours(probe)
        valid = nb >= 0
        if not valid.any():
            return 0.0
        return float(search.mask[nb[valid]].mean())

    def _draw_local(self, rng: np.random.Generator, seeds: np.ndarray) -> np.ndarray:
        """``(L, 3)`` pool positions drawn among the seeds' neighbours, pairwise >= t_l apart
        (the seed itself where no such neighbour is left, which fails the spread test)."""
        assert self._spread_x is not None and self._spread_y is not None, \
            "local draws need local sampling"
        nb = self.neighbours(seeds)
        free = nb >= 0  # (L, k) candidates still allowed
        safe = np.maximum(nb, 0)
        # x and y apart, sets first, as _apart_sets takes them.
        px = np.take(self._spread_x, safe, axis=1)  # (sets, L, k)
        py = np.take(self._spread_y, safe, axis=1)
        sets = px.shape[0]
        row_start = np.arange(len(seeds)) * nb.shape[1]  # flat index of each row's first
        out = np.empty((len(seeds), 3), dtype=np.int64)
        for j in range(3):
            key = np.where(free, rng.random(free.shape), -1.0)
            at = row_start + np.argmax(key, axis=1)  # flat index of each row's pick
            found = free.reshape(-1).take(at)  # key >= 0 there: a free candidate's key
            out[:, j] = np.where(found, nb.reshape(-1).take(at), seeds)
            if j < 2:  # what the last pick leaves free is not used
                free &= _apart_sets(px - px.reshape(sets, -1).take(at, axis=1)[:, :, None],
                                    py - py.reshape(sets, -1).take(at, axis=1)[:, :, None],
                                    self._t2)
        return out

    def draw(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """``(size, 4)`` global match indices, seed match first."""
        n = len(self.pool)
        seeds = rng.integers(0, n, size)
        others = rng.integers(0, n, (size, 3))
        if self.local:
            is_local = np.flatnonzero(rng.random(size) < self.fraction)
            if len(is_local):
                others[is_local] = self._draw_local(rng, seeds[is_local])
        return self.pool[np.concatenate([seeds[:, None], others], axis=1)]


def _required(search: _Search, sampler: _Sampler, n: int, cfg: FilterConfig) -> float:
    """Adaptive iteration bound for the current best model (``max_iters`` before any)."""
    if search.count <= 0:
        return float(cfg.max_iters)
    return _required_iters(search.count / n, sampler.local_inlier_fraction(search),
                           sampler.fraction, cfg.confidence)


class NumpyScoring:
    """The heavy kernels of a RANSAC run (minimal solver, bounds, singular-value test, full
    scoring), in numpy on the CPU: the default. Its torch twin, for any torch device, is
    :class:`~colmap_miho.filtering.torch_scoring.TorchScoring`; sampling, the search's
    bookkeeping and the refit stay in numpy for both.

    ``prefetch``: 0 scores exactly the hypotheses the search reaches; ``> 0`` screens them
    ahead in chunks of that many (then doubling), which gives the same result with fewer
    calls (round trips to a device; numpy call overhead on the CPU) (:class:`_BatchScores`).
    """

    #: Measured on the CPU: per-call overhead dominates groups of 4 hypotheses, so screening
    #: ahead (4, 8, 16, ... at a time; at most twice the work the search needs) is faster.
    prefetch = 4

    def _work(self) -> _Scratch:
        """This instance's work arrays (created on first use; one instance per filter
        call)."""
        work = self.__dict__.get("_scratch")
        if work is None:
            work = self.__dict__["_scratch"] = _Scratch()
        return work

    def hypotheses(self, problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                   ok: np.ndarray, pool: np.ndarray, t2: float) -> tuple[Hypotheses, np.ndarray]:
        """:func:`hypotheses_from_samples` and their :func:`one_way_count` on ``pool``."""
        hyp = hypotheses_from_samples(problem, sample, cfg, ok)
        if not len(hyp):
            return hyp, np.zeros(0, dtype=np.int64)
        return hyp, self.one_way_count(problem, hyp, pool, t2)

    def one_way_count(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray,
                      t2: float) -> np.ndarray:
        """:func:`one_way_count`, with work arrays kept for the next call."""
        return one_way_count(problem, hyp, idx, t2, scratch=self._work())

    def singular_value_ok(self, problem: Problem, hyp: Hypotheses,
                          cfg: FilterConfig) -> np.ndarray:
        """:func:`passes_singular_value_test`."""
        return passes_singular_value_test(problem, hyp, cfg)

    def error_sq(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> np.ndarray:
        """:func:`error_sq`, float64 ``(K, n)`` numpy."""
        return error_sq(problem, hyp, idx, self._work())

    def masks(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray,
              t2: float) -> tuple[np.ndarray, np.ndarray | None]:
        """``(masks, err)``: the inliers ``err <= t2`` ``(K, n)`` and the errors (``None``
        where the kernel does not bring them back: here, :func:`inlier_masks` skips the
        errors of matches already outside)."""
        return inlier_masks(problem, hyp, idx, t2, self._work()), None

    def screen(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray, t2: float,
               cfg: FilterConfig) -> tuple[np.ndarray, np.ndarray]:
        """``(sv_ok, masks)``: the singular-value test ``(K,)`` and the inlier masks
        ``(K, n)`` of all ``K`` hypotheses (rows failing the test are not used: here they are
        left empty)."""
        sv = self.singular_value_ok(problem, hyp, cfg)
        if sv.all():  # the usual case: no copy of the hypotheses, no scatter of the masks
            return sv, self.masks(problem, hyp, idx, t2)[0]
        masks = np.zeros((len(hyp), len(idx)), dtype=bool)
        if sv.any():
            masks[sv] = self.masks(problem, hyp.take(np.flatnonzero(sv)), idx, t2)[0]
        return sv, masks


class _BatchScores:
    """Full scores of one batch's hypotheses ``hyp`` (sorted by their one-way bound ``ub``),
    computed on demand for the positions :func:`_score_batch` reaches.

    With ``scoring.prefetch == 0`` exactly the positions asked for are scored (singular-value
    test, then the errors of the survivors). Otherwise positions are screened ahead, in
    chunks of ``prefetch`` that double, never past ``reach`` (the positions the loop can
    reach at all, set by the best count when the batch starts); the search takes the same
    hypotheses in the same order, so the result is the same.
    """

    def __init__(self, scoring: NumpyScoring, problem: Problem, hyp: Hypotheses, ub: np.ndarray,
                 pool: np.ndarray, cfg: FilterConfig, t2: float, reach: int) -> None:
        self.scoring, self.problem, self.hyp, self.ub = scoring, problem, hyp, ub
        self.pool, self.cfg, self.t2, self.reach = pool, cfg, t2, reach
        self.chunk = scoring.prefetch
        self.done = 0
        if self.chunk:
            self.sv = np.zeros(reach, dtype=bool)
            self.mask = np.zeros((reach, len(pool)), dtype=bool)

    def get(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(keep, masks, err)`` for the positions ``pos``: those passing the singular-value
        test, their inlier masks and (when at hand) errors on the pool."""
        if not self.chunk:
            keep = pos[self.scoring.singular_value_ok(self.problem, self.hyp.take(pos), self.cfg)]
            if not len(keep):
                return keep, np.zeros((0, len(self.pool)), dtype=bool), None
            masks, err = self.scoring.masks(self.problem, self.hyp.take(keep), self.pool, self.t2)
            return keep, masks, err
        if len(pos) and pos[-1] >= self.done:
            stop = min(max(int(pos[-1]) + 1, self.done + self.chunk), self.reach)
            todo = np.arange(self.done, stop)
            todo = todo[self.ub[todo] > 0]
            if len(todo):
                self.sv[todo], self.mask[todo] = self.scoring.screen(
                    self.problem, self.hyp.take(todo), self.pool, self.t2, self.cfg)
            self.done = stop
            self.chunk *= 2
        keep = pos[self.sv[pos]]
        return keep, self.mask[keep], None


def _score_batch(problem: Problem, hyp: Hypotheses, ub: np.ndarray, pool: np.ndarray,
                 cfg: FilterConfig, search: _Search, stats: dict, scoring: NumpyScoring) -> bool:
    """Full-score the hypotheses of one batch that can matter; returns whether the best
    model changed.

    Full scoring runs in descending order of the one-way upper bound, in small groups, until
    no remaining bound can beat the best count; the batch's two strongest (at least n
    possible inliers) are always scored, as buffer candidates. ``ub`` ``(K,)``: the one-way
    bounds of ``hyp`` on ``pool`` (:func:`one_way_count`).
    """
    order = np.argsort(-ub, kind="stable")
    ub = ub[order]
    n_buf = int(np.count_nonzero(ub[: min(2, cfg.buffer_size)] >= cfg.inlier_count))
    # The best count only rises, so no group starting past the bounds above it is reached.
    first = max(int(np.count_nonzero(ub > search.count)), n_buf)
    reach = min(len(ub), -(-first // 4) * 4)
    scores = _BatchScores(scoring, problem, hyp.take(order), ub, pool, cfg, search.t2, reach)
    improved = False
    start = 0
    while start < len(order) and (ub[start] > search.count or start < n_buf):
        pos = np.arange(start, min(start + 4, len(order)))
        start += 4
        keep, masks, err = scores.get(pos[ub[pos] > 0])
        if not len(keep):
            continue
        stats["full_scored"] += len(keep)
        improved |= search.consider(scores.hyp.take(keep), masks, err)
    return improved


def _refit_best(problem: Problem, pool: np.ndarray, cfg: FilterConfig, search: _Search,
                stats: dict, scoring: NumpyScoring) -> None:
    """Replace the best model by least-squares refits on its inliers while they lose none
    (the refit itself runs in numpy; its errors through ``scoring``)."""
    assert search.hyp is not None and search.mask is not None, "no best model"
    for _ in range(cfg.refit_iters):
        refit = _refit(problem, search.hyp, pool[search.mask])
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
    """Run one RANSAC search on the matches ``pool`` (``(n,)`` global indices).

    Args:
        buffer: the global top-z buffer of sub-optimal hypotheses; evaluated first
            (bootstrap) and returned updated.
        candidates: the problem's local-sampling candidates, shared by the rounds (built
            here when ``None``).
        scoring: where the heavy kernels run (``None``: :class:`NumpyScoring`).

    Returns:
        ``(result, buffer)``; ``result`` is ``None`` when no valid hypothesis was found.
    """
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
    sampler = _Sampler(problem, pool, cfg, candidates)
    required = _required(search, sampler, n, cfg)
    # Iterations are the samples that pass the spread test: a draw that fails it is not a
    # hypothesis and counts neither towards c_min / c_max nor against the adaptive bound
    # (samples rejected by the reflection or quasi-affinity checks do count: they are
    # hypotheses found wrong). A pool where almost no sample is spread out stops after
    # _DRAW_CAP x c_max draws.
    while (stats["samples"] < (target := max(cfg.min_iters, min(required, cfg.max_iters)))
           and stats["drawn"] < _DRAW_CAP * cfg.max_iters):
        # Small batches while the bound may still drop, bigger ones when it will not; sized
        # by the share of spread-out draws so far.
        size = cfg.batch_size
        if search.count > 0:
            rate = max(stats["samples"] / max(stats["drawn"], 1), 0.05)
            size = int(min(max(size, (target - stats["samples"]) / rate), 8 * size))
        sample = sampler.draw(rng, size)
        stats["drawn"] += size
        ok = spread_ok(problem, sample, cfg.t_l)
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
    buffer = _greedy_buffer(search.cands, search.mask, cfg.buffer_size)
    stats["required_iters"] = required
    return RoundResult(search.hyp, search.err, search.count, stats), buffer


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
