"""The least-squares matching step of the NCC refinement and its acceptance rule.

From the NCC peak, LSM (:func:`.align.lsm_align`, compiled on CPU tensors) replaces NCC's position
only if it converged regularly, stayed within ``lsm_max_shift_px`` of the peak (else it found
another minimum) and its shift's standard deviation is below ``lsm_max_sigma_px``. With
``lsm_antialias`` the finer of two views is smoothed to the coarser one's blur, each sample the mean
of 4 bicubic reads."""

from __future__ import annotations

import torch

from ...validation import MAX_BLUR_PX
from ..config import NCCConfig
from ..warping import ImageStack, frame_jacobian, job_images, local_scale
from . import kernel
from .align import frame_sampler, lsm_align

#: smallest anti-aliasing blur (pixels of the finer view) applied; a side that needs less is
#: read unsmoothed (4 samples per pixel are not spent on a blur below the pixel scale).
MIN_BLUR_PX = 0.2
#: counters of :func:`lsm_step`, in the refine stats.
LSM_COUNTERS = ("lsm_applied", "lsm_not_converged", "lsm_far", "lsm_imprecise")


def lsm_step(
    img_f: torch.Tensor | ImageStack,
    img_m: torch.Tensor | ImageStack,
    H_f_inv: torch.Tensor,
    frame_f: torch.Tensor,
    H_m_inv: torch.Tensor,
    frame_m: torch.Tensor,
    offset: torch.Tensor,
    cfg: NCCConfig,
    *,
    compiled: bool | None = None,
) -> tuple[torch.Tensor, dict[str, int], torch.Tensor]:
    """LSM-refined offsets ``(n, 2)`` of n matches (LSM's where accepted, else ``offset``), the
    :data:`LSM_COUNTERS`, and ``(n,)`` which matches LSM moved.

    ``H_f_inv``, ``H_m_inv`` ``(n, 3, 3)`` common frame -> image pixels; ``frame_f``, ``frame_m``
    ``(n, 2)`` keypoints in the frame; ``offset`` the NCC offset (LSM's start). ``compiled``: the
    kernel (None: where the tensors are on the CPU)."""
    n = offset.shape[0]
    if n == 0:
        return offset, dict.fromkeys(LSM_COUNTERS, 0), torch.zeros(0, dtype=torch.bool,
                                                                   device=offset.device)
    radius = cfg.lsm_window
    dev = offset.device
    if compiled is None:
        compiled = dev.type == "cpu"
    r, rows = radius, torch.arange(n, device=dev)
    k = rows.numel()
    eye = torch.eye(2, dtype=torch.float64, device=dev).expand(k, 2, 2)
    zero = torch.zeros((k, 2), dtype=torch.float64, device=dev)
    sub_f, sub_m = job_images(img_f, rows), job_images(img_m, rows)
    every = torch.arange(k, device=dev)
    blur_f = blur_m = None
    if cfg.lsm_antialias > 0:
        blur_f, blur_m = _antialias_blur(H_f_inv[rows], frame_f[rows], H_m_inv[rows],
                                         frame_m[rows] + offset[rows], cfg.lsm_antialias)
    if compiled:
        res = kernel.lsm_frames(sub_f, sub_m, H_f_inv[rows], frame_f[rows], H_m_inv[rows],
                                frame_m[rows], offset[rows], r, blur_f=blur_f, blur_m=blur_m,
                                affine=cfg.lsm_affine, max_iterations=cfg.lsm_max_iterations,
                                tol_px=cfg.lsm_tol_px, max_shift_px=cfg.lsm_max_shift_px)
    else:
        samp_f = frame_sampler(sub_f, H_f_inv[rows], frame_f[rows], blur_px=blur_f)
        samp_m = frame_sampler(sub_m, H_m_inv[rows], frame_m[rows], blur_px=blur_m)
        res = lsm_align(samp_m, samp_f(every, eye, zero, r), offset[rows],
                        affine=cfg.lsm_affine, max_iterations=cfg.lsm_max_iterations,
                        tol_px=cfg.lsm_tol_px, max_shift_px=cfg.lsm_max_shift_px)
    shift, sigma_max, converged = res.shift, res.sigma_max, res.converged
    outcome = lsm_outcomes(shift - offset, sigma_max, converged, cfg)
    ok = outcome["applied"]
    counts = {f"lsm_{key}": int(mask.sum()) for key, mask in outcome.items()}
    return torch.where(ok[:, None], shift, offset), counts, ok


def _antialias_blur(H_f_inv: torch.Tensor, at_f: torch.Tensor, H_m_inv: torch.Tensor,
                    at_m: torch.Tensor, base_px: float
                    ) -> tuple[tuple[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
    """The ``blur_px`` arguments that smooth each match's finer view to the coarser one's blur."""
    s_f = local_scale(frame_jacobian(H_f_inv, at_f))
    s_m = local_scale(frame_jacobian(H_m_inv, at_m))
    coarse = torch.minimum(s_f, s_m)
    sg_f, sg_m = blur_sigma(s_f, coarse, base_px), blur_sigma(s_m, coarse, base_px)
    return (sg_f >= MIN_BLUR_PX, sg_f), (sg_m >= MIN_BLUR_PX, sg_m)


def lsm_outcomes(moved: torch.Tensor, sigma_max: torch.Tensor, converged: torch.Tensor,
                 cfg: NCCConfig) -> dict[str, torch.Tensor]:
    """The acceptance rule of n LSM results: disjoint ``(n,)`` masks ``applied``, ``not_converged``,
    ``far``, ``imprecise``."""
    far = moved.abs().amax(dim=1) > cfg.lsm_max_shift_px
    imprecise = converged & ~far & ~(sigma_max <= cfg.lsm_max_sigma_px)
    return {"applied": converged & ~far & ~imprecise, "not_converged": ~converged & ~far,
            "far": far, "imprecise": imprecise}


def blur_sigma(scale: torch.Tensor, coarse: torch.Tensor, base_px: float) -> torch.Tensor:
    """``(n,)`` Gaussian sigma (own pixels) bringing a view of ``scale`` to a coarser ``coarse``:
    ``base_px * sqrt(ratio^2 - 1)``, 0 where not finer, at most ``MAX_BLUR_PX``."""
    ratio = scale / coarse.clamp_min(1e-12)
    # capped: a blur wider than any window it smooths is meaningless (a degenerate frame's
    # scale ratio is huge), and the compiled kernel sizes its buffers by it
    return (base_px * (ratio.square() - 1).clamp_min(0).sqrt()).clamp_max(MAX_BLUR_PX)


def smoothing_to(J: torch.Tensor, scale: torch.Tensor, coarse: torch.Tensor,
                 base_px: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``blur`` argument smoothing a view to a coarser view's blur (see :func:`blur_sigma`),
    where it reaches ``MIN_BLUR_PX``."""
    sigma = blur_sigma(scale, coarse, base_px)
    # one step of sigma image pixels along the image's axes, in frame pixels: J^-1 sigma
    return sigma >= MIN_BLUR_PX, torch.linalg.inv(J) * sigma[:, None, None]
