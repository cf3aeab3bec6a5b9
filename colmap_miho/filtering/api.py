"""Public entry point of the MOP / MOP+MiHo match filter.

``filter_matches(pts1, pts2)`` runs MOP (paper Sec. 3.1), MOP* (App. D), MOP+MiHo (Sec. 3.2) or the
VSAC half-homography split on ``(N, 2)`` pixel matches and returns the survivors, each one's
homography, and the homography pairs that bring both images into one frame for refinement.

Departures from the paper, each a :class:`FilterConfig` field: guided minimal samples (``sampling``)
that pass the spread test, with an adaptive bound that counts only those; both homographies eligible
when a match fits exactly two (``assignment``); ``miho_threshold`` full match while searching,
half-matches at keep time; the rotation fix may pick a mirrored image 2
(``rotation_fix_reflections``), only by a clear margin. Numpy on the CPU by default (latency
dominates these small batched operations); with a torch ``device`` the heavy kernels run there with
the same samples."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..arguments import FILTER_SEED_BOUND, check_integer
from ..enums import FilterMethod, MihoThreshold
from .assign import assign_matches
from .coherence import incoherent_planes
from .config import FilterConfig
from .homography import adjugate, to_unit_h33
from .miho import apply_affine, build_problem, choose_rotation, sqrt_split
from .mop import MopOutput, run_mop
from .problem import Hypotheses
from .torch_scoring import scoring_for_device

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class FilterResult:
    """Outcome of :func:`filter_matches` for one pair (``N`` matches, ``K`` homographies).

    Attributes:
        inliers: bool ``(N,)``, the matches kept.
        labels: int64 ``(N,)``, each kept match's homography index, -1 for discarded ones.
        homographies: float64 ``(K, 3, 3)`` ``H_2from1`` (pixels, integer = pixel centre).
        patch_homographies: float64 ``(K, 2, 3, 3)`` pairs ``(A, B)`` with ``A x1 ~ B x2`` into one
          common frame (MiHo: the midpoint frame).
        success: at least one homography was found (otherwise nothing is kept).
        method: the variant that ran.
        stats: per-stage seconds and counters; ``reason`` when ``success`` is False.
    """

    inliers: np.ndarray
    labels: np.ndarray
    homographies: np.ndarray
    patch_homographies: np.ndarray
    success: bool
    method: FilterMethod
    stats: dict = field(default_factory=dict)

    @property
    def num_inliers(self) -> int:
        """Number of kept matches."""
        return int(self.inliers.sum())

    @property
    def num_homographies(self) -> int:
        """Number of homographies ``K``."""
        return int(self.homographies.shape[0])


def _as_points(x, name: str) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor on any device
        x = x.detach().cpu().numpy()
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an (N, 2) array of pixel coordinates: {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {tuple(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def _failure(n: int, method: FilterMethod, stats: dict, reason: str) -> FilterResult:
    stats["reason"] = reason
    return FilterResult(
        inliers=np.zeros(n, dtype=bool), labels=np.full(n, -1, dtype=np.int64),
        homographies=np.zeros((0, 3, 3)), patch_homographies=np.zeros((0, 2, 3, 3)),
        success=False, method=method, stats=stats)


def filter_matches(pts1, pts2, *, method: str | FilterMethod | None = None,
                   config: FilterConfig | None = None, seed: int = 0,
                   progress: bool = False, device: str | torch.device | None = "cpu") -> FilterResult:
    """Filter two-view matches with MOP / MOP* / MOP+MiHo / MOP+MiHo* / MOP+VSAC.

    Args:
        pts1, pts2: ``(N, 2)`` float pixels (integer = pixel centre), ``pts2[i]`` matched to
          ``pts1[i]``; numpy arrays or torch tensors.
        method: the variant; replaces ``config.method`` when given (default ``"mop_miho"``).
        config: parameters; ``None`` = paper defaults.
        seed: integer in [0, 2^32 - 1]; same inputs, config and seed give identical results.
        device: ``"cpu"`` (numpy) or a torch device for the heavy kernels; outputs are numpy.

    Returns a :class:`FilterResult`; degenerate input (fewer than 4 matches, no plane) gives
    ``success=False``. Raises ``ValueError`` for bad shapes, non-finite values, seed, method or
    device."""
    check_integer("seed", seed, FILTER_SEED_BOUND)
    t0 = time.perf_counter()
    scoring = scoring_for_device(device)
    x1 = _as_points(pts1, "pts1")
    x2 = _as_points(pts2, "pts2")
    if len(x1) != len(x2):
        raise ValueError(f"pts1 and pts2 must have the same length, got {len(x1)} and {len(x2)}")
    cfg = _resolve_config(method, config)
    n = len(x1)
    stats: dict = {"matches": n}
    if n < 4:
        return _failure(n, cfg.method, stats, "fewer than 4 matches")

    rng = np.random.default_rng(seed)
    t1 = time.perf_counter()
    G = _rotation_fix(x1, x2, cfg, rng, stats)
    if G is None:
        # MiHo's midpoint frame degenerates for a mirrored pair; the star variants assume
        # no reflections, so such a pair is rejected rather than filtered into garbage.
        stats["time_total"] = time.perf_counter() - t0
        return _failure(n, cfg.method, stats, "mirrored pair rejected by the reflection check")
    x2r = apply_affine(G, x2) if stats["rotation_index"] else x2
    t2 = time.perf_counter()

    problem = build_problem(x1, x2r, miho=cfg.is_miho, full_match=cfg.miho_threshold != MihoThreshold.HALF)
    mop = run_mop(problem, cfg, rng, progress=progress, scoring=scoring)
    stats.update(mop.stats)
    t3 = time.perf_counter()
    stats.update(time_validate=t1 - t0, time_rotation=t2 - t1, time_mop=t3 - t2)
    if len(mop.hyps) == 0:
        stats["time_total"] = time.perf_counter() - t0
        return _failure(n, cfg.method, stats, "no homography with enough inliers")

    if cfg.miho_threshold == MihoThreshold.FULL_SEARCH and cfg.is_miho:
        problem = build_problem(x1, x2r, miho=True, full_match=False)  # keep: half-match
    err2 = scoring.error_sq(problem, mop.hyps, np.arange(n))
    hyps, labels, support = _assign(x1, x2, mop, err2, cfg, stats)
    t4 = time.perf_counter()
    H, patch = _homographies_and_patch_pairs(hyps, G, cfg, stats)
    t5 = time.perf_counter()
    stats.update(time_assign=t4 - t3, time_split=t5 - t4, time_total=t5 - t0,
                 support=support.tolist())
    return FilterResult(
        inliers=labels >= 0, labels=labels, homographies=to_unit_h33(H),
        patch_homographies=to_unit_h33(patch), success=True, method=cfg.method, stats=stats)


def _resolve_config(method: str | FilterMethod | None, config: FilterConfig | None) -> FilterConfig:
    if config is None:
        return FilterConfig(method=FilterMethod.MOP_MIHO if method is None else FilterMethod.parse(method, "method"))
    if not isinstance(config, FilterConfig):
        raise ValueError(f"config must be a FilterConfig, got {type(config).__name__}")
    if method is not None:
        return dataclasses.replace(config, method=FilterMethod.parse(method, "method"))
    return config


def _assign(x1: np.ndarray, x2: np.ndarray, mop: MopOutput, err2: np.ndarray, cfg: FilterConfig,
            stats: dict) -> tuple[Hypotheses, np.ndarray, np.ndarray]:
    """``(hyps, labels, support)``: MOP's homographies that stay, each match's label ``(N,)`` and
    each homography's support ``(K,)``, from the keep-time errors ``err2`` ``(K, N)``."""
    hyps, round_inliers = mop.hyps, mop.round_inliers
    labels, support = assign_matches(err2, cfg.t_l, rule=cfg.assignment, round_inliers=round_inliers)
    if cfg.coherence:
        drop = incoherent_planes(x1, x2, labels, err2 <= cfg.t_l**2)
        stats["coherence_dropped"] = len(drop)
        if len(drop):
            alive = np.setdiff1d(np.arange(len(hyps)), drop)
            hyps, err2, round_inliers = hyps.take(alive), err2[alive], round_inliers[alive]
            labels, support = assign_matches(err2, cfg.t_l, rule=cfg.assignment,
                                             round_inliers=round_inliers)
    return hyps, labels, support


def _rotation_fix(x1: np.ndarray, x2: np.ndarray, cfg: FilterConfig, rng: np.random.Generator,
                  stats: dict) -> np.ndarray | None:
    """MiHo's pre-alignment ``G`` ``(3, 3)`` of image 2 (identity when off); None for a mirrored
    pair when the method rejects reflections."""
    if not (cfg.rotation_fix and (cfg.is_miho or cfg.method == FilterMethod.MOP_VSAC)):
        stats["rotation_index"] = 0
        return np.eye(3)
    G, idx, _ = choose_rotation(x1, x2, rng, pairs=cfg.rotation_pairs,
                                reflections=cfg.rotation_fix_reflections)
    stats["rotation_index"] = idx
    if idx >= 4 and cfg.reflection_check:
        return None
    return G


def _homographies_and_patch_pairs(hyps, G: np.ndarray, cfg: FilterConfig,
                                  stats: dict) -> tuple[np.ndarray, np.ndarray]:
    """``H_2from1`` ``(K, 3, 3)`` in the original image 2 and the patch pairs ``(K, 2, 3, 3)``, from
    hypotheses fitted against image 2 pre-aligned by ``G``."""
    G_inv = np.linalg.inv(G)
    K = len(hyps)
    if cfg.is_miho:
        H1, H2 = hyps.H[:, 0], hyps.H[:, 1]
        return G_inv @ H2 @ H1, np.stack([H1, adjugate(H2) @ G], axis=1)
    Hr = hyps.H[:, 0]
    H = G_inv @ Hr
    patch = np.stack([np.broadcast_to(np.eye(3), (K, 3, 3)), adjugate(H)], axis=1)
    if cfg.method == FilterMethod.MOP_VSAC:
        fallbacks = []
        for k in range(K):
            Hv = sqrt_split(Hr[k])
            if Hv is None:
                fallbacks.append(k)
            else:
                patch[k] = (Hv, adjugate(Hv) @ G)
        stats["vsac_fallbacks"] = fallbacks
    return H, patch
