"""The least-squares matching step of the NCC refinement and its acceptance rule.

After the NCC peak of a match (integer peak and parabola), the template around the fixed keypoint and the
search image around the moving keypoint are both read in the match's common frame (the
winning homography pair of the NCC search), bicubically, and aligned by :func:`.lsm.lsm_align`
from the NCC offset. LSM's position replaces the NCC one only where

- the Gauss-Newton iteration converged with a regular affine map and gain,
- the shift stays within ``lsm_max_shift_px`` of the NCC peak (a larger move means LSM found
  another minimum than the correlation did), and
- the a-posteriori standard deviation of the shift is below ``lsm_max_sigma_px`` (flat and
  edge-like patches, and patches the model does not fit, fail this);

elsewhere the NCC refinement goes on as without LSM (iterated parabolas). Each reason is
counted.
"""

from __future__ import annotations

import torch

from .config import NCCConfig
from .lsm import frame_sampler, lsm_align
from .warping import ImageStack

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
) -> tuple[torch.Tensor, dict[str, int], torch.Tensor]:
    """LSM-refined offsets of n matches, the counters of :data:`LSM_COUNTERS`, and which
    matches LSM moved.

    Args:
        img_f, img_m: (H, W) float32 fixed-side and moving-side images, or
            :class:`~.warping.ImageStack` objects with one image per match (n rows).
        H_f_inv, H_m_inv: (n, 3, 3) float64 common frame -> image pixels of each side.
        frame_f, frame_m: (n, 2) float64 common-frame positions of the fixed and the moving
            keypoint.
        offset: (n, 2) float64 NCC offset of the moving side (common frame): the start of
            LSM and the reference of ``lsm_max_shift_px``.
        cfg: ``lsm_*`` fields of :class:`~.config.NCCConfig`.
    Returns:
        ((n, 2) float64 offsets: LSM's where accepted, else ``offset``; counters; (n,)
        bool accepted).
    """
    n = offset.shape[0]
    if n == 0:
        return offset, dict.fromkeys(LSM_COUNTERS, 0), torch.zeros(0, dtype=torch.bool,
                                                                   device=offset.device)
    radius = cfg.lsm_radius or cfg.template_radius
    dev = offset.device
    rows = torch.arange(n, device=dev)
    eye = torch.eye(2, dtype=torch.float64, device=dev).expand(n, 2, 2)
    zero = torch.zeros((n, 2), dtype=torch.float64, device=dev)
    tpl = frame_sampler(img_f, H_f_inv, frame_f)(rows, eye, zero, radius)
    res = lsm_align(frame_sampler(img_m, H_m_inv, frame_m), tpl, offset,
                    affine=cfg.lsm_affine, max_iterations=cfg.lsm_max_iterations, tol_px=cfg.lsm_tol_px,
                    max_shift_px=cfg.lsm_max_shift_px)
    far = (res.shift - offset).abs().amax(dim=1) > cfg.lsm_max_shift_px
    not_conv = ~res.converged & ~far
    imprecise = res.converged & ~far & ~(res.sigma_max <= cfg.lsm_max_sigma_px)
    ok = res.converged & ~far & ~imprecise
    counts = {
        "lsm_applied": int(ok.sum()),
        "lsm_not_converged": int(not_conv.sum()),
        "lsm_far": int(far.sum()),
        "lsm_imprecise": int(imprecise.sum()),
    }
    return torch.where(ok[:, None], res.shift, offset), counts, ok
