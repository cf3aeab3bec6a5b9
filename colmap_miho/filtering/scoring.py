"""The heavy kernels of a RANSAC run in numpy: minimal solver with quasi-affine signs,
singular-value test, one-way bound, full errors and masks (squared pixels; a match's error is the
max over halves and directions, ``inf`` where a projection breaks the sample's sign)."""

from __future__ import annotations

import math

import numpy as np

from .compiled import sampling as sampling_kernels
from .compiled import scoring as kernels
from .config import FilterConfig
from .homography import (
    adjugate,
    dlt_singular_value,
    four_point,
    one_way_inside,
    transfer_error_sq,
)
from .problem import Hypotheses, Problem
from .sampling import checked_samples, spread_ok


def sample_signs(problem: Problem, H: np.ndarray, Hinv: np.ndarray, sample: np.ndarray):
    """``(ok (K,), sign, sign_inv (K, halves))``: whether the 4 sample points' ``w`` share one
    nonzero sign in every half and direction, for ``H``, ``Hinv`` ``(K, halves, 3, 3)`` and samples
    ``(K, 4)``."""
    ok = np.ones(len(H), dtype=bool)
    signs = []
    for mat, pts in ((H, problem.src_all), (Hinv, problem.dst_all)):
        p = pts[sample]  # (K, 4, halves, 2)
        w = (mat[:, None, :, 2, :2] * p).sum(-1) + mat[:, None, :, 2, 2]  # (K, 4, halves)
        sg = np.sign(w)
        ok &= np.all(sg == sg[:, :1], axis=(1, 2)) & np.all(sg[:, 0] != 0, axis=1)
        signs.append(sg[:, 0])
    return ok, signs[0], signs[1]


def _per_half(pts_all: np.ndarray, sample: np.ndarray) -> np.ndarray:
    """``(B * halves, 4, 2)`` sample points, half by half (``np.take``: faster, the same values)."""
    N, nh, _ = pts_all.shape
    B = len(sample)
    rows = np.take(pts_all.reshape(N, nh * 2), sample, axis=0)  # (B, 4, halves * 2)
    return rows.reshape(B, 4, nh, 2).transpose(0, 2, 1, 3).reshape(B * nh, 4, 2)


def _one_sign(sg: np.ndarray) -> np.ndarray:
    """``(B,)`` bool: in every half the 4 signs of ``sg`` are one nonzero sign."""
    ok = sg[:, :, 0] * sg[:, :, 1] > 0
    ok &= sg[:, :, 0] * sg[:, :, 2] > 0
    ok &= sg[:, :, 0] * sg[:, :, 3] > 0
    return ok.all(axis=1)


def hypotheses_from_samples(problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                            ok: np.ndarray | None = None):
    """The surviving :class:`Hypotheses` of samples ``(B, 4)``: spread test (unless ``ok`` is
    given), reflection check, quasi-affinity. The singular-value test is separate, to run only where
    it matters."""
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
    """``(K,)`` bool: every half's minimal DLT system passes ``cfg.min_singular_value`` (App. A.3)."""
    K, nh = len(hyp), problem.num_halves
    src = _per_half(problem.src_all, hyp.sample)
    dst = _per_half(problem.dst_all, hyp.sample)
    sv = dlt_singular_value(src, dst).reshape(K, nh)
    return np.all(sv > cfg.min_singular_value, axis=1)


def error_sq(problem: Problem, hyp: Hypotheses, idx: np.ndarray,
             scratch: _Scratch | None = None) -> np.ndarray:
    """Squared MOP error ``(K, n)`` of hypotheses on the matches ``idx``, times ``error_scale**2``."""
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
    """Work arrays reused between calls (a fresh large numpy array pays page faults on every call);
    not for sharing between threads."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}
        self._points_of: tuple[Problem, np.ndarray] | None = None
        self._points: tuple[tuple[np.ndarray, np.ndarray], ...] | None = None
        self._points32: tuple[np.ndarray, np.ndarray] | None = None
        self._stacked: np.ndarray | None = None
        self._all_of: tuple[Problem, np.ndarray] | None = None

    def _pool(self, problem: Problem, idx: np.ndarray) -> None:
        """Forget the pool's arrays unless the same ``problem`` and ``idx`` objects come back."""
        key = self._points_of
        if key is None or key[0] is not problem or key[1] is not idx:
            self._points = self._points32 = self._stacked = None
            self._points_of = (problem, idx)

    def points(self, problem: Problem, idx: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """Per half, ``(src, dst)`` of the matches ``idx`` as contiguous ``(2, n)`` arrays."""
        self._pool(problem, idx)
        if self._points is None:
            self._points = tuple((problem.src[h][idx].T.copy(), problem.dst[h][idx].T.copy())
                                 for h in range(problem.num_halves))
        return self._points

    def stacked(self, problem: Problem, idx: np.ndarray) -> np.ndarray:
        """:meth:`points` as one ``(halves, 2, 2, n)`` array, gathered in one call."""
        self._pool(problem, idx)
        if self._stacked is None:
            if self._all_of is None or self._all_of[0] is not problem:
                every = np.stack([np.stack([problem.src[h].T, problem.dst[h].T])
                                  for h in range(problem.num_halves)])
                self._all_of = (problem, every)
            self._stacked = np.take(self._all_of[1], idx, axis=3)
        return self._stacked

    def points32(self, problem: Problem, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first half's ``(src, dst)`` in float32."""
        self._pool(problem, idx)
        if self._points32 is None:
            first = self._points[0] if self._points is not None else self.stacked(problem, idx)[0]
            self._points32 = (first[0].astype(np.float32), first[1].astype(np.float32))
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
    """``(K, n)`` bool: ``error_sq(problem, hyp, idx) <= t2`` with the same decisions, term by term,
    carrying on only matches some hypothesis still keeps (exact: the error is a max, the scale a
    power of two, and sign-scaling each homography turns the sign test into ``w > 0``)."""
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
    """Inliers ``(K,)`` under the first half's forward error: an upper bound of the full count.
    Division-free float32 in cache-sized blocks of hypotheses."""
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


class NumpyScoring:
    """The heavy kernels of a RANSAC run in numpy on the CPU (the default; the torch twin is
    :class:`~colmap_miho.filtering.torch_scoring.TorchScoring`). ``prefetch > 0`` screens hypotheses
    ahead in growing chunks: the same result with fewer calls."""

    #: On the CPU per-call overhead dominates groups of 4 hypotheses, so screening ahead
    #: (4, 8, 16, ... at a time; at most twice the work the search needs) pays (numpy; the
    #: compiled path scores a whole batch in one call, :meth:`score_batch`).
    prefetch = 4
    #: Whether the batch kernels run compiled (set per instance by the constructor; a
    #: subclass that does not call it keeps numpy).
    compiled = False

    def __init__(self, compiled: bool = True) -> None:
        """``compiled``: run the batch kernels compiled by numba; ``False`` runs the numpy reference."""
        self.compiled = compiled

    def spread_ok(self, problem: Problem, sample: np.ndarray, t_l: float) -> np.ndarray:
        """:func:`~.sampling.spread_ok` (compiled or numpy)."""
        if self.compiled:
            assert problem.spread_xy is not None, "sampling runs on the numpy problem"
            return sampling_kernels.spread_ok(problem.spread_xy, sample, t_l**2)
        return spread_ok(problem, sample, t_l)

    def _work(self) -> _Scratch:
        work = self.__dict__.get("_scratch")
        if work is None:
            work = self.__dict__["_scratch"] = _Scratch()
        return work

    def hypotheses(self, problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                   ok: np.ndarray, pool: np.ndarray, t2: float) -> tuple[Hypotheses, np.ndarray]:
        """:func:`hypotheses_from_samples` and their :func:`one_way_count` on ``pool``."""
        if self.compiled:
            src, dst = self._work().points32(problem, pool)
            H, Hinv, sign, sign_inv, smp, ub = kernels.hypotheses(
                sample, ok, problem.x1, problem.x2, problem.src_all, problem.dst_all,
                cfg.reflection_check, src, dst, t2 / problem.error_scale**2)
            return Hypotheses(H, Hinv, sign, sign_inv, smp), ub
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
        if self.compiled:
            return kernels.singular_value_ok(hyp.sample, problem.src_all, problem.dst_all,
                                             cfg.min_singular_value)
        return passes_singular_value_test(problem, hyp, cfg)

    def error_sq(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> np.ndarray:
        """:func:`error_sq`, float64 ``(K, n)`` numpy (compiled: the same bits)."""
        if self.compiled:
            return kernels.error_sq(hyp.H, hyp.Hinv, hyp.sign, hyp.sign_inv,
                                    self._work().stacked(problem, idx), problem.error_scale**2)
        return error_sq(problem, hyp, idx, self._work())

    def masks(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray,
              t2: float) -> tuple[np.ndarray, np.ndarray | None]:
        """``(masks (K, n), err)``; ``err`` is None here (masks skip matches already outside)."""
        if self.compiled:
            s2 = problem.error_scale**2
            if math.frexp(s2)[0] == 0.5:  # a power of two: as inlier_masks does
                t2, s2 = t2 / s2, 1.0
            return kernels.inlier_masks(hyp.H, hyp.Hinv, hyp.sign, hyp.sign_inv,
                                        self._work().stacked(problem, idx), t2, s2), None
        return inlier_masks(problem, hyp, idx, t2, self._work()), None

    def screen(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray, t2: float,
               cfg: FilterConfig) -> tuple[np.ndarray, np.ndarray]:
        """``(sv_ok (K,), masks (K, n))`` of all hypotheses (failing rows left empty)."""
        sv = self.singular_value_ok(problem, hyp, cfg)
        if sv.all():  # the usual case: no copy of the hypotheses, no scatter of the masks
            return sv, self.masks(problem, hyp, idx, t2)[0]
        masks = np.zeros((len(hyp), len(idx)), dtype=bool)
        if sv.any():
            masks[sv] = self.masks(problem, hyp.take(np.flatnonzero(sv)), idx, t2)[0]
        return sv, masks

    def score_batch(self, problem: Problem, hyp: Hypotheses, ub: np.ndarray, idx: np.ndarray,
                    cfg: FilterConfig, t2: float, count: int, have_best: bool):
        """:func:`.compiled.scoring.score_batch` of ``hyp`` with bounds ``ub`` (compiled only)."""
        assert self.compiled, "the fused batch scoring is compiled"
        s2 = problem.error_scale**2
        if math.frexp(s2)[0] == 0.5:  # a power of two: as inlier_masks does
            t2, s2 = t2 / s2, 1.0
        return kernels.score_batch(ub, count, have_best, cfg.inlier_count, cfg.buffer_size,
                                   hyp.H, hyp.Hinv, hyp.sign, hyp.sign_inv, hyp.sample,
                                   problem.src_all, problem.dst_all, cfg.min_singular_value,
                                   self._work().stacked(problem, idx), t2, s2)
