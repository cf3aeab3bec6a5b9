"""The filter's heavy RANSAC kernels in torch float64 on any torch device, with the numpy path's
formulas in the same order; sampling and bookkeeping stay in numpy, so both agree up to ties."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from ..devices import resolve_device
from .config import FilterConfig
from .homography import adjugate, dlt_singular_value, four_point, one_way_inside, project
from .problem import Hypotheses, Problem
from .sampling import checked_samples
from .scoring import NumpyScoring

if TYPE_CHECKING:
    import torch

def scoring_for_device(device: str | torch.device | None = "cpu") -> NumpyScoring:
    """The kernels for ``device``; ValueError for an unknown or unusable device."""
    if device is None or (isinstance(device, str) and device == "cpu"):
        return NumpyScoring()
    try:
        import torch  # noqa: F401 - the torch kernels need it
    except ImportError:
        raise ValueError(f"device {device!r} needs torch, which is not installed") from None
    resolved = resolve_device(device)  # the one device grammar
    if isinstance(device, str) and device.lower() == "auto" and resolved.type != "cuda":
        return NumpyScoring()
    return TorchScoring(resolved)


class TorchScoring(NumpyScoring):
    """:class:`~.scoring.NumpyScoring`'s kernels in torch float64 on ``device`` (numpy in and out);
    the problem's points go to the device once per problem, each pool once per round."""

    def __init__(self, device: Any) -> None:
        import torch

        self.torch = torch
        self.device = torch.device(device)
        on_gpu = self.device.type != "cpu"
        # Screening ahead costs little on a GPU and saves round trips; on the CPU it is
        # extra arithmetic, so only a little.
        self.prefetch = 64 if on_gpu else 8
        self._bound_block = 1 << 22 if on_gpu else 131072  # elements per one-way block
        self._problems: dict[int, tuple[Problem, Any]] = {}
        self._pool: tuple[np.ndarray, Any] | None = None
        self._points: tuple | None = None

    # -- transfers ------------------------------------------------------------------------
    def _tensor(self, a: np.ndarray) -> Any:
        return self.torch.as_tensor(a, device=self.device)

    def _problem(self, problem: Problem) -> Any:
        """The device copy of ``problem`` (kept alive with it, so its id stays unique)."""
        hit = self._problems.get(id(problem))
        if hit is None or hit[0] is not problem:
            dev = Problem(src=tuple(self._tensor(a) for a in problem.src),
                          dst=tuple(self._tensor(a) for a in problem.dst),
                          spread=tuple(self._tensor(a) for a in problem.spread),
                          x1=self._tensor(problem.x1), x2=self._tensor(problem.x2),
                          error_scale=problem.error_scale)
            hit = (problem, dev)
            self._problems[id(problem)] = hit
        return hit[1]

    def _index(self, idx: np.ndarray) -> Any:
        if self._pool is None or self._pool[0] is not idx:
            self._pool = (idx, self._tensor(idx))
        return self._pool[1]

    def _hyp(self, hyp: Hypotheses) -> tuple[Any, Any]:
        """``(mats, signs)`` on the device: ``(K, 2 halves, 3, 3)`` homographies then adjugates."""
        K, nh = len(hyp), hyp.H.shape[1]
        packed = self._tensor(np.concatenate(
            [hyp.H.reshape(K, -1), hyp.Hinv.reshape(K, -1), hyp.sign, hyp.sign_inv], axis=1))
        mats = packed[:, :18 * nh].reshape(K, 2 * nh, 3, 3)
        return mats, packed[:, 18 * nh:]

    def _pool_points(self, problem: Problem, idx: np.ndarray) -> tuple[Any, Any]:
        """Source and destination points ``(2 halves, n, 2)`` of ``idx`` in :meth:`_hyp`'s order."""
        hit = self._points
        if hit is None or hit[0] is not problem or hit[1] is not idx:
            P, ix = self._problem(problem), self._index(idx)
            src = P.src_all[ix].transpose(0, 1)  # (halves, n, 2)
            dst = P.dst_all[ix].transpose(0, 1)
            hit = self._points = (problem, idx, (self.torch.cat([src, dst]),
                                                 self.torch.cat([dst, src])))
        return hit[2]

    @staticmethod
    def _host(t: Any) -> np.ndarray:
        return t.cpu().numpy()

    # -- kernels --------------------------------------------------------------------------
    def hypotheses(self, problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                   ok: np.ndarray, pool: np.ndarray, t2: float) -> tuple[Hypotheses, np.ndarray]:
        """Hypotheses and their one-way bounds on ``pool`` on the device, one transfer back."""
        sample = checked_samples(problem, sample, cfg, ok)
        nh = problem.num_halves
        B = len(sample)
        if not B:
            return Hypotheses.empty(nh), np.zeros(0, dtype=np.int64)
        P = self._problem(problem)
        s = self._tensor(sample)
        src = P.src_all[s].permute(0, 2, 1, 3).reshape(B * nh, 4, 2)
        dst = P.dst_all[s].permute(0, 2, 1, 3).reshape(B * nh, 4, 2)
        solved: Any = four_point(src, dst)  # tensors: the maths is shared with numpy
        H, s_fwd, s_inv = solved
        H = H.reshape(B, nh, 3, 3)
        s_fwd = s_fwd.reshape(B, nh, 4)
        s_inv = s_inv.reshape(B, nh, 4)
        good = self.torch.isfinite(H).flatten(1).all(1)
        for sg in (s_fwd, s_inv):
            good &= (sg == sg[:, :, :1]).flatten(1).all(1) & (sg[:, :, 0] != 0).all(1)
        Hinv: Any = adjugate(H)
        # The bound of every sample (the invalid ones are dropped on the host).
        ub = self._bounds(problem, (H[:, 0] * s_fwd[:, 0, :1, None]).to(self.torch.float32),
                          pool, t2)
        packed = self._host(self.torch.cat(
            [H.reshape(B, -1), Hinv.reshape(B, -1), s_fwd[:, :, 0], s_inv[:, :, 0],
             ub[:, None].to(H.dtype), good[:, None].to(H.dtype)], dim=1))
        keep = packed[:, -1] > 0
        packed = packed[keep]
        k = 9 * nh
        hyp = Hypotheses(packed[:, :k].reshape(-1, nh, 3, 3),
                         packed[:, k:2 * k].reshape(-1, nh, 3, 3),
                         packed[:, 2 * k:2 * k + nh], packed[:, 2 * k + nh:2 * k + 2 * nh],
                         sample[keep])
        return hyp, packed[:, -2].astype(np.int64)

    def one_way_count(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray,
                      t2: float) -> np.ndarray:
        """:func:`~.scoring.one_way_count` (float32, division-free) on the device."""
        Hs = self._tensor((hyp.H[:, 0] * hyp.sign[:, 0, None, None]).astype(np.float32))
        return self._host(self._bounds(problem, Hs, idx, t2)).astype(np.int64)

    def _bounds(self, problem: Problem, Hs: Any, idx: np.ndarray, t2: float) -> Any:
        """One-way inlier counts ``(K,)`` of the sign-scaled first-half homographies ``Hs``."""
        torch = self.torch
        t2 = t2 / problem.error_scale**2
        P, ix = self._problem(problem), self._index(idx)
        src = P.src[0][ix].to(torch.float32)
        dst = P.dst[0][ix].to(torch.float32)
        X, Y, x2, y2 = src[:, 0], src[:, 1], dst[:, 0], dst[:, 1]
        n, K = len(idx), Hs.shape[0]
        if K == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        Hs = Hs.reshape(K, 9, 1)
        counts = []
        kb = max(1, self._bound_block // max(n, 1))
        for a in range(0, K, kb):
            counts.append(one_way_inside(Hs[a:a + kb], X, Y, x2, y2, t2).sum(1))
        return torch.cat(counts)

    def singular_value_ok(self, problem: Problem, hyp: Hypotheses,
                          cfg: FilterConfig) -> np.ndarray:
        """:func:`~.scoring.passes_singular_value_test` on the device."""
        return self._host(self._sv_ok(problem, self._tensor(hyp.sample), cfg))

    def _sv_ok(self, problem: Problem, sample: Any, cfg: FilterConfig) -> Any:
        """:func:`~.scoring.passes_singular_value_test` of the samples ``(K, 4)`` (device)."""
        P = self._problem(problem)
        K, nh = sample.shape[0], problem.num_halves
        src = P.src_all[sample].permute(0, 2, 1, 3).reshape(K * nh, 4, 2)
        dst = P.dst_all[sample].permute(0, 2, 1, 3).reshape(K * nh, 4, 2)
        sv = dlt_singular_value(src, dst).reshape(K, nh)
        return (sv > cfg.min_singular_value).all(1)

    def _error_sq(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> Any:
        """:func:`~.scoring.error_sq` ``(K, n)`` on the device, all halves and directions at once
        (a masked fill: boolean assignment would synchronise a GPU)."""
        mats, signs = self._hyp(hyp)
        a, b = self._pool_points(problem, idx)
        projected: Any = project(mats, a)  # tensors (K, 2 halves, n)
        x, y, w = projected
        e = (x - b[..., 0]) ** 2 + (y - b[..., 1]) ** 2
        e.masked_fill_(self.torch.sign(w) != signs[..., None], math.inf)
        err = e.amax(dim=1)
        if problem.error_scale != 1.0:
            err *= problem.error_scale**2
        return err

    def error_sq(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> np.ndarray:
        """:func:`~.scoring.error_sq` on the device, brought back as float64 numpy."""
        return self._host(self._error_sq(problem, hyp, idx))

    def masks(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray,
              t2: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Inlier masks only (the errors stay on the device)."""
        return self._host(self._error_sq(problem, hyp, idx) <= t2), None

    def screen(self, problem: Problem, hyp: Hypotheses, idx: np.ndarray, t2: float,
               cfg: FilterConfig) -> tuple[np.ndarray, np.ndarray]:
        """Singular-value test and inlier masks together (one transfer back)."""
        sv = self._sv_ok(problem, self._tensor(hyp.sample), cfg)
        masks = self._error_sq(problem, hyp, idx) <= t2
        both = self._host(self.torch.cat([sv[:, None], masks], dim=1))
        return both[:, 0], both[:, 1:]
