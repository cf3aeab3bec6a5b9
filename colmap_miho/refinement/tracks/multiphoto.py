"""Joint multi-photo least-squares matching of whole tracks, after the walk (after Gruen &
Baltsavias): the anchor fixes the frame and every other observation is aligned to a leave-one-out
consensus template (one holding its own patch would pull it towards where it is). Rejected
observations keep the walk's position."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import NCCConfig
from ..lsm.align import frame_sampler, lsm_align
from ..lsm.step import lsm_outcomes, smoothing_to
from ..warping import ImageStack, frame_jacobian, local_scale

#: tracks with fewer observations (reference included) are left to the walk.
MIN_OBSERVATIONS = 3
#: observations per batched call at most (whole tracks; a larger track is a call alone).
CHUNK_OBSERVATIONS = 4096
#: counters of the joint pass, in the refine stats: tracks and non-reference observations
#: aligned, the outcome of each observation, and the pass's wall-clock seconds.
MULTIPHOTO_COUNTERS = ("joint_tracks", "joint_observations", "joint_applied",
                       "joint_not_converged", "joint_far", "joint_imprecise", "joint_seconds")


@dataclass(frozen=True)
class JointResult:
    """Output of :func:`joint_lsm` (N observations, common-frame pixels): ``shift`` ``(N, 2)``,
    ``sigma_max`` ``(N,)``, ``accepted`` ``(N,)`` (never a reference) and the ``joint_*`` counts."""

    shift: torch.Tensor
    sigma_max: torch.Tensor
    accepted: torch.Tensor
    counts: dict


def joint_lsm(
    images: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    track: torch.Tensor,
    is_ref: torch.Tensor,
    cfg: NCCConfig,
    iterations: int,
    *,
    star_first: bool = False,
) -> JointResult:
    """Align the observations of tracks jointly to leave-one-out consensus templates.

    Args:
        images: ``(H, W)`` float32 or an :class:`~..warping.ImageStack` with one image per observation.
        H_inv: ``(N, 3, 3)`` common frame (reference image pixels) -> observation pixels.
        centres: ``(N, 2)`` the track's reference keypoint in the common frame.
        track: ``(N,)`` int64 track index 0..T-1; is_ref: ``(N,)`` one reference per track.
        iterations: consensus passes (stop early when no accepted shift moves by ``lsm_tol_px``).
        star_first: one pass against the reference alone first; needed from a poor start, since
          a consensus pass removes only part of the template's misalignment.
    """
    if iterations < 0 or iterations + star_first < 1:
        raise ValueError(f"joint_lsm needs a pass: iterations={iterations}, star_first={star_first}")
    N = H_inv.shape[0]
    dev, f64 = H_inv.device, torch.float64
    if N == 0:
        return JointResult(torch.zeros((0, 2), dtype=f64, device=dev),
                           torch.zeros(0, dtype=f64, device=dev),
                           torch.zeros(0, dtype=torch.bool, device=dev),
                           dict.fromkeys(MULTIPHOTO_COUNTERS[2:6], 0))
    T = int(track.max()) + 1
    radius = cfg.lsm_window
    blur = (_coarsest_blur(H_inv, centres, track, T, cfg.lsm_antialias)
            if cfg.lsm_antialias > 0 else None)
    samp = frame_sampler(images, H_inv, centres, blur=blur)
    ref_of = torch.zeros(T, dtype=torch.int64, device=dev)
    ref_rows = torch.nonzero(is_ref)[:, 0]
    ref_of[track[ref_rows]] = ref_rows
    mov = torch.nonzero(~is_ref)[:, 0]
    every = torch.arange(N, device=dev)
    eye = torch.eye(2, dtype=f64, device=dev).expand(N, 2, 2).clone()
    t = torch.zeros((N, 2), dtype=f64, device=dev)
    A = eye.clone()
    g0 = samp(every, A, t, radius).reshape(N, -1)
    r0_init, r1_init = _match_to(g0, g0[ref_of[track]])
    r0, r1 = r0_init.clone(), r1_init.clone()
    member = torch.ones(N, dtype=torch.bool, device=dev)
    sigma = torch.full((N,), float("inf"), dtype=f64, device=dev)
    conv = torch.zeros(N, dtype=torch.bool, device=dev)

    def sub(rows: torch.Tensor, A_: torch.Tensor, t_: torch.Tensor, r: int) -> torch.Tensor:
        return samp(mov[rows], A_, t_, r)

    passes = [True] * star_first + [False] * iterations  # True: the reference alone
    for it, star in enumerate(passes):
        g = g0 if it == 0 else samp(every, A, t, radius).reshape(N, -1)
        tpl = _leave_one_out(r0[:, None] + r1[:, None] * g.to(f64), is_ref if star else member,
                             track, T)
        side = 2 * radius + 1
        res = lsm_align(sub, tpl[mov].to(torch.float32).view(-1, side, side), t[mov],
                        affine=cfg.lsm_affine, max_iterations=cfg.lsm_max_iterations,
                        tol_px=cfg.lsm_tol_px, max_shift_px=cfg.lsm_max_shift_px)
        prev = t[mov].clone()
        t[mov], A[mov], r0[mov], r1[mov] = res.shift, res.affine, res.offset, res.gain
        sigma[mov], conv[mov] = res.sigma_max, res.converged
        ok = lsm_outcomes(t[mov], sigma[mov], conv[mov], cfg)["applied"]
        member[mov] = ok
        bad = mov[~ok]  # restart from the walk's position, out of the template
        t[bad], A[bad], r0[bad], r1[bad] = 0.0, eye[bad], r0_init[bad], r1_init[bad]
        moved = (res.shift - prev)[ok].abs()
        if it > star_first and (moved.numel() == 0 or float(moved.max()) < cfg.lsm_tol_px):
            break
    shift = torch.where(member[:, None] & ~is_ref[:, None], t, 0.0)
    last = lsm_outcomes(res.shift, res.sigma_max, res.converged, cfg)
    accepted = member & ~is_ref
    counts = {"joint_applied": int(accepted.sum()),
              **{f"joint_{key}": int(last[key].sum()) for key in ("not_converged", "far", "imprecise")}}
    sigma_out = torch.where(is_ref, float("inf"), sigma)
    return JointResult(shift, sigma_out, accepted, counts)


def _match_to(g: torch.Tensor, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(r0, r1)`` ``(n,)`` with ``r0 + r1 g`` matching f's mean and spread (r1 = 1 where flat)."""
    g, f = g.to(torch.float64), f.to(torch.float64)
    gm, fm = g.mean(dim=1), f.mean(dim=1)
    gs, fs = (g - gm[:, None]).std(dim=1), (f - fm[:, None]).std(dim=1)
    r1 = torch.where((gs > 1e-12) & (fs > 1e-12), fs / gs.clamp_min(1e-12), torch.ones_like(gs))
    return fm - r1 * gm, r1


def _leave_one_out(v: torch.Tensor, member: torch.Tensor, track: torch.Tensor, T: int) -> torch.Tensor:
    """``(N, P)``: for each observation the mean of its track's member patches other than its own."""
    w = member.to(v.dtype)
    total = torch.zeros((T, v.shape[1]), dtype=v.dtype, device=v.device).index_add_(0, track, v * w[:, None])
    count = torch.zeros(T, dtype=v.dtype, device=v.device).index_add_(0, track, w)
    own = (count[track] - w).clamp_min(1.0)
    return (total[track] - v * w[:, None]) / own[:, None]


def _coarsest_blur(H_inv: torch.Tensor, centres: torch.Tensor, track: torch.Tensor,
                   T: int, base_px: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``blur`` argument of :func:`..lsm.align.frame_sampler` that smooths every observation to
    its track's coarsest view, so that the consensus carries one blur."""
    J = frame_jacobian(H_inv, centres)
    s = local_scale(J)
    s_min = torch.full((T,), float("inf"), dtype=s.dtype, device=s.device)
    s_min = s_min.scatter_reduce(0, track, s, reduce="amin")
    return smoothing_to(J, s, s_min[track], base_px)
