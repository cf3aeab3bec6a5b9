"""Public entry point of the MOP / MOP+MiHo match filter.

``filter_matches(pts1, pts2)`` runs the paper's MOP (Sec. 3.1, App. A), MOP* (App. D),
MOP+MiHo (Sec. 3.2, App. B, C) or the VSAC half-homography split on ``(N, 2)`` pixel matches,
and returns which matches survive, the homography each one is assigned to, and the
homography pairs that bring both images into one common frame for patch-based refinement.

Where this implementation departs from the paper (each one a :class:`FilterConfig` field):

- ``sampling``: guided (NAPSAC-style) minimal samples by default, so that they pass the
  spread test, with an adaptive bound that accounts for it; ``"uniform"`` is the paper's.
  c_min, c_max and the bound count the samples that pass the spread test (a draw that fails
  it is no hypothesis). One-way pre-scoring is an exact bound, not an approximation.
- ``assignment``: the paper's median rule, with both homographies eligible when a match is
  compatible with exactly two (as in the reference; the plain median would always pick the
  larger plane); ``"median"`` and the reference's round-based rule are options.
- ``max_failures``: 3 failures in a row (paper); the reference stops at the 4th.
- ``t_h``: t_l / 2 (paper; the reference uses 7 px).
- ``miho_threshold``: what MiHo's thresholds bound (half-match errors as in the paper, the
  full match, or the full match while searching and half-matches at keep time, the
  default). The half-match tolerance in the search lets planes that mix in gross outliers
  win rounds; the full-match tolerance at keep time drops correct matches on non-planar
  scenes.
- ``rotation_fix_reflections``: the rotation fix (MOP+MiHo and VSAC) may also pick a
  mirrored image 2 (App. C's suggested extension); it keeps the identity unless another
  candidate wins by a clear margin (3 standard deviations on the same random pairs), so
  that outlier noise cannot turn an upright pair. For MOP+MiHo* a pair whose best
  pre-alignment is mirrored fails (``success=False``): MiHo's midpoint frame degenerates
  there and the star variants assume no reflections.

``device``: numpy on the CPU by default (torch inputs are copied to the CPU); with a torch
device the heavy RANSAC kernels run in torch there while sampling (same seed, same samples)
and the bookkeeping stay in numpy, giving the same result up to floating-point ties
(:mod:`.torch_scoring`). A MOP round is a chain of small batched operations on
``(hypotheses, matches)`` arrays where per-call latency, not arithmetic, dominates, which is
why numpy stays the CPU default.

Speed comes from the closed-form minimal solver and sample signs (no SVD per hypothesis),
exact one-way pre-scoring, full scoring only where it can change the best model, guided
sampling with adaptive stopping, and explained matches leaving the pool.
"""

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
    """Outcome of :func:`filter_matches` for one image pair (``N`` input matches, ``K``
    homographies).

    Attributes:
        inliers: bool ``(N,)``, the matches kept.
        labels: int64 ``(N,)``, index into ``homographies`` of each kept match's assigned
            homography, -1 for discarded matches.
        homographies: float64 ``(K, 3, 3)``, ``H_2from1`` mapping image-1 pixels to image-2
            pixels (integer = pixel centre), scaled so that ``H[2, 2] = 1`` when possible.
        patch_homographies: float64 ``(K, 2, 3, 3)``, pairs ``(A, B)`` mapping both images
            into one common frame, ``A x1 ~ B x2`` for the cluster's matches: ``(I, H^-1)``
            for MOP and MOP*; ``(H1, H2^-1)`` for MiHo (image 1 -> midpoint frame, image 2
            -> midpoint frame, rotation fix folded into ``B``); ``(H_v, H_v^-1)`` for VSAC
            (rotation fix folded into ``B``), falling back to ``(I, H^-1)`` where the square
            root fails (listed in ``stats["vsac_fallbacks"]``).
        success: at least one homography was found (otherwise nothing is kept).
        method: the variant that ran.
        stats: seconds per stage (``time_*``), MOP ``rounds``, ``failures``, hypotheses
            ``drawn``/``valid``/``full_scored``, ``support`` per homography, the rotation
            fix's choice (``rotation_index``: 0-3 = k*90 degrees, 4-7 mirrored), ``reason``
            when ``success`` is False.
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
        pts1: ``(N, 2)`` float pixels in image 1 (integer = pixel centre); numpy array or
            torch tensor (CPU or CUDA, copied to the CPU).
        pts2: ``(N, 2)`` float pixels in image 2, ``pts2[i]`` matched to ``pts1[i]``.
        method: filter variant (:class:`~colmap_miho.enums.FilterMethod` or its value). Rule:
            when given, it wins (it replaces ``config.method``); when ``None`` the method is
            ``config.method``, or ``"mop_miho"`` when ``config`` is ``None`` too.
        config: parameters; ``None`` = paper defaults.
        seed: seed of the ``numpy.random.Generator`` that drives all sampling, an integer in
            [0, 2^32 - 1]; the same inputs, config and seed give identical results.
        progress: show a tqdm bar over MOP rounds.
        device: where the heavy RANSAC kernels run: ``"cpu"`` (default, numpy),
            ``"cuda"`` / ``"cuda:N"`` / any torch device string or ``torch.device`` object
            (torch float64 on that device; ``torch.device("cpu")`` runs the torch path on
            the CPU). Sampling stays in numpy with the same generator, so every
            device draws the same samples; results agree up to floating-point ties.
            Outputs are numpy arrays on every device.

    Returns:
        :class:`FilterResult`. Degenerate input (fewer than 4 matches, duplicated or
        collinear points, no plane with ``n`` inliers) gives ``success=False`` and nothing
        kept.

    Raises:
        ValueError: wrong shapes, length mismatch, NaN/inf (naming the argument), a seed
            that is not an integer in range, an unknown method, or a device that is unknown
            or not available.
    """
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
    """The config that runs: ``method``, when given, replaces ``config.method``."""
    if config is None:
        return FilterConfig(method=FilterMethod.MOP_MIHO if method is None else FilterMethod.parse(method, "method"))
    if not isinstance(config, FilterConfig):
        raise ValueError(f"config must be a FilterConfig, got {type(config).__name__}")
    if method is not None:
        return dataclasses.replace(config, method=FilterMethod.parse(method, "method"))
    return config


def _assign(x1: np.ndarray, x2: np.ndarray, mop: MopOutput, err2: np.ndarray, cfg: FilterConfig,
            stats: dict) -> tuple[Hypotheses, np.ndarray, np.ndarray]:
    """``(hyps, labels, support)``: MOP's homographies that stay (all but the incoherent ones
    when ``cfg.coherence``), each match's label ``(N,)`` and each homography's support
    ``(K,)`` (:func:`assign_matches`), from the squared keep-time errors ``err2`` ``(K, N)``
    of MOP's homographies on the matches ``x1``, ``x2`` ``(N, 2)``."""
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
    """MiHo's pre-alignment ``G`` ``(3, 3)`` applied to image 2 (identity when off), recording
    ``stats["rotation_index"]``; ``None`` when the pair is mirrored and the method rejects
    reflections."""
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
    """``H_2from1`` ``(K, 3, 3)`` in the original image 2 and the patch pairs ``(K, 2, 3, 3)``
    of :class:`FilterResult`, from MOP's hypotheses fitted against image 2 pre-aligned by
    ``G``; VSAC records the square roots that failed in ``stats["vsac_fallbacks"]``."""
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
