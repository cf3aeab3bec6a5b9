"""The least-squares matching step of the NCC refinement and its acceptance rule.

After the NCC peak of a match (integer peak and parabola), the template around the fixed keypoint and the
search image around the moving keypoint are both read in the match's common frame (the
winning homography pair of the NCC search), bicubically, and aligned by :func:`.align.lsm_align`
from the NCC offset. LSM's position replaces the NCC one only where

- the Gauss-Newton iteration converged with a regular affine map and gain,
- the shift stays within ``lsm.max_shift_px`` of the NCC peak (a larger move means LSM found
  another minimum than the correlation did), and
- the a-posteriori standard deviation of the shift is below ``lsm.max_sigma_px`` (flat and
  edge-like patches, and patches the model does not fit, fail this);

elsewhere the NCC refinement goes on as without LSM (iterated parabolas). Each reason is
counted.

On CPU tensors the step runs :func:`.kernel.lsm_frames`, one compiled loop
per match; the torch path (:func:`.align.frame_sampler` and :func:`.align.lsm_align`) runs on
CUDA and is the kernel's reference (they agree to float rounding).

Anti-aliasing (``lsm.antialias`` > 0): where one view sees the match at a finer scale than
the other (the local scale ``sqrt |det J|`` of its frame -> image map at the match is
larger), its samples are smoothed so that both sides carry the blur of the coarser view:
a Gaussian of ``lsm_antialias * sqrt(ratio^2 - 1)`` of its own pixels (the coarser view's
blur, ``lsm.antialias`` pixels of its own, brought to the finer view's pixels, less the
finer view's own). The Gaussian is approximated by the mean of 4 bicubic samples at
``(+-sigma, +-sigma)`` image pixels from each sample's position, along the image axes (the
variance of a Gaussian of ``sigma`` on each axis; the mean is separable, so the compiled
kernel reads it as one sample with the 4 samples' taps merged), so the smoothing costs
samples at the affected matches only and stays per match; a
3 x 3 stencil of the same variance was measured slightly more accurate at over twice the cost.
Smoothing whole images once per blur level instead (kornia's ``gaussian_blur2d``) would cost
more than the samples: an image is loaded many times per run and a match's blur varies
continuously. Smoothing a crop around each match once costs about what the samples it saves
cost, as the crop must cover the whole iteration. A 3-sample stencil of the same mean and
covariance (a triangle) skews the blur and loses accuracy (docs/results.md).
"""

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
    """LSM-refined offsets of n matches, the counters of :data:`LSM_COUNTERS`, and which
    matches LSM moved.

    Args:
        img_f, img_m: (H, W) float32 fixed-side and moving-side images, or
            :class:`~..warping.ImageStack` objects with one image per match (n rows).
        H_f_inv, H_m_inv: (n, 3, 3) float64 common frame -> image pixels of each side.
        frame_f, frame_m: (n, 2) float64 common-frame positions of the fixed and the moving
            keypoint.
        offset: (n, 2) float64 NCC offset of the moving side (common frame): the start of
            LSM and the reference of ``lsm.max_shift_px``.
        cfg: ``lsm_*`` fields of :class:`~..config.NCCConfig`.
        compiled: run :func:`.kernel.lsm_frames` (CPU tensors only) rather than the
            torch path (:func:`.align.frame_sampler` and :func:`.align.lsm_align`); None: where
            the tensors are on the CPU.
    Returns:
        ((n, 2) float64 offsets: LSM's where accepted, else ``offset``; counters; (n,)
        bool accepted).
    """
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
    if cfg.lsm.antialias > 0:
        blur_f, blur_m = _antialias_blur(H_f_inv[rows], frame_f[rows], H_m_inv[rows],
                                         frame_m[rows] + offset[rows], cfg.lsm.antialias)
    if compiled:
        res = kernel.lsm_frames(sub_f, sub_m, H_f_inv[rows], frame_f[rows], H_m_inv[rows],
                                frame_m[rows], offset[rows], r, blur_f=blur_f, blur_m=blur_m,
                                affine=cfg.lsm.affine, max_iterations=cfg.lsm.max_iterations,
                                tol_px=cfg.lsm.tol_px, max_shift_px=cfg.lsm.max_shift_px)
    else:
        samp_f = frame_sampler(sub_f, H_f_inv[rows], frame_f[rows], blur_px=blur_f)
        samp_m = frame_sampler(sub_m, H_m_inv[rows], frame_m[rows], blur_px=blur_m)
        res = lsm_align(samp_m, samp_f(every, eye, zero, r), offset[rows],
                        affine=cfg.lsm.affine, max_iterations=cfg.lsm.max_iterations,
                        tol_px=cfg.lsm.tol_px, max_shift_px=cfg.lsm.max_shift_px)
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
    far = moved.abs().amax(dim=1) > cfg.lsm.max_shift_px
    imprecise = converged & ~far & ~(sigma_max <= cfg.lsm.max_sigma_px)
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
