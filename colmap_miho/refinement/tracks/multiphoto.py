"""Joint multi-photo least-squares matching of whole tracks, after the walk.

The walk aligns each keypoint to one fixed neighbour (the anchor, or a partner that may have
moved itself), whose patch alone is the template. Here every track of at least ``MIN_OBSERVATIONS``
observations is aligned jointly, in the spirit of multi-photo LSM (Gruen & Baltsavias): the
reference observation (the track's anchor, which never moves) defines the geometry (the
common frame is the anchor image's pixels, centred on the anchor keypoint), and every other
observation is aligned by :func:`..lsm.align.lsm_align` (affine + gain/offset) to a *consensus
template*: the mean of the track's patches, each read at its current alignment and brought
to the reference's radiometry (``r0 + r1 g``), the reference's own patch included. The
passes iterate (rebuild the template -> align), starting from the walk's positions (or, with
``star_first``, from one pass against the reference alone).

With the reference held fixed, each view's error at the joint fixed point is, to first order
in the image noise, its own noise less the reference's, as for the star of pairwise
alignments to the reference: the reference's noise is common to the track (a consistent
shift of the point in the reference frame). The consensus changes the non-linear part: a
template that is not one view's appearance, so more patches converge and pass the precision
gate. Each consensus pass removes only part of the template's misalignment (the other views'
errors are in it), so from a poor start the star pass should come first.

Each observation's template leaves its own patch out (leave-one-out mean): a template that
held it would pull the alignment towards its current position by a share of 1 / (number of
patches). Observations not accepted in a pass (see below) leave the template for the next
one and restart from the walk's position. A track of 3 observations thus aligns each
non-reference view to the mean of the reference and the other view.

Maps between views: the walk composes, for every keypoint it reached, the patch homography
pairs along its chain from the anchor (:attr:`.refine_calls.WalkState.to_ref`: anchor-image
pixels -> its image pixels). Its translation is replaced by the walk's result (the chain maps
the anchor keypoint to the walk's position), so the pass starts where the walk ended and the
chain only supplies the local shape of the map, which LSM's affine refines.

Acceptance is the pairwise LSM step's (:mod:`..lsm.step`): converged at the last pass, the
shift from the walk's position within ``lsm.max_shift_px``, the shift's a-posteriori
standard deviation below ``lsm.max_sigma_px``. An accepted observation moves to
``H_inv (c + t)``; the others keep the walk's result. Every observation is thus aligned
relative to the same fixed reference; its final position is the walk's or this pass's.

Anti-aliasing (``lsm.antialias`` > 0): every observation is smoothed to the blur of the
track's coarsest view (the smallest local scale ``sqrt |det J|`` of its frame -> image map),
with :mod:`..lsm.step`'s 4-sample Gaussian, so all patches of the consensus carry one blur.

Batched in torch on the device of the walk; observations are processed in chunks of whole
tracks, one LSM radius (``NCCConfig.lsm_window``) for all.
"""

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
        images: (H, W) float32 image, or an :class:`~..warping.ImageStack` with one image per
            observation (N rows).
        H_inv: (N, 3, 3) float64 common frame (the track's reference image pixels) -> the
            observation's image pixels; ``H_inv[o] (centres[o])`` is its start position.
        centres: (N, 2) float64 the track's reference keypoint (common frame), the same for
            all observations of a track.
        track: (N,) int64 track of each observation, 0..T-1.
        is_ref: (N,) bool, exactly one reference per track (held fixed; its ``H_inv`` maps
            the frame to its own image).
        cfg: ``lsm_*`` fields of :class:`~..config.NCCConfig` (radius, affine, iterations,
            tolerance, shift and precision bounds, anti-aliasing).
        iterations: consensus passes (rebuild the template -> align), >= 0; stops
            early once no accepted shift changes by ``lsm.tol_px``.
        star_first: before them, one pass that aligns every observation to the reference
            alone (the star of pairwise alignments), so that the first consensus template
            is built from aligned patches. Needed from a poor start: each consensus pass
            removes only part of the template's misalignment (the other views' errors are
            in it). After the walk the start is already aligned.
    Returns:
        :class:`JointResult`.
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
    blur = (_coarsest_blur(H_inv, centres, track, T, cfg.lsm.antialias)
            if cfg.lsm.antialias > 0 else None)
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
                        affine=cfg.lsm.affine, max_iterations=cfg.lsm.max_iterations,
                        tol_px=cfg.lsm.tol_px, max_shift_px=cfg.lsm.max_shift_px)
        prev = t[mov].clone()
        t[mov], A[mov], r0[mov], r1[mov] = res.shift, res.affine, res.offset, res.gain
        sigma[mov], conv[mov] = res.sigma_max, res.converged
        ok = lsm_outcomes(t[mov], sigma[mov], conv[mov], cfg)["applied"]
        member[mov] = ok
        bad = mov[~ok]  # restart from the walk's position, out of the template
        t[bad], A[bad], r0[bad], r1[bad] = 0.0, eye[bad], r0_init[bad], r1_init[bad]
        moved = (res.shift - prev)[ok].abs()
        if it > star_first and (moved.numel() == 0 or float(moved.max()) < cfg.lsm.tol_px):
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
