"""Least-squares matching (LSM, Gruen 1985): batched Gauss-Newton alignment of patches.

Per match j a fixed reference template ``f_j(u)`` (offsets ``u`` of a (2r+1)^2 grid, common
frame pixels) is aligned to the search image ``G_j`` (the moving side, seen in the match's
common frame) by the model

    f(u) + e(u) = r0 + r1 * G(t + A u)

with the 2x2 affine ``A``, the shift ``t`` (common-frame pixels, relative to the match's
centre), the radiometric offset ``r0`` and gain ``r1``: 8 parameters (4 with
``affine=False``: shift and radiometry only). Gauss-Newton in the forward-compositional form:
the increment is applied in the patch frame, ``t + A (u + d + D u)``, so the Jacobian uses the
gradient of the resampled patch itself (central differences over a grid one pixel wider than
the template) and the update is ``t += A d``, ``A = A (I + D)``. Each match stops once its
shift update is below ``tol_px``; the a-posteriori covariance of the shift is
``A (s0^2 N^-1)_dd A^T`` with ``s0^2 = e^T e / (n - p)`` (n pixels, p parameters) and N the
normal matrix of the last iteration.

Sampling is bicubic (``grid_sample(mode="bicubic")``, Keys a = -0.75): bilinear sampling
biases the values towards pixel centres (``tests/refinement/test_lsm.py`` measures the
bilinear bias against bicubic on a known warp). The gradients are central differences of the
bicubic samples, taken with :meth:`torch.Tensor.__getitem__` slices rather than kornia's
``spatial_gradient``: kornia's pads and runs a 3x3 ``conv2d`` over the batch, which is several
times slower than two subtractions on these small patches (``benchmarks/results/lsm.md``) and
whose rounding may depend on the batch size (oneDNN picks kernels by shape).
kornia's warps (``warp_affine``, ``warp_perspective``) sample whole images on a regular grid,
not per-match point sets in several images, so they are not used either.

On the CPU a match's result is bitwise the same whatever the other matches of the call: the
sample positions are elementwise products, every reduction runs over one match's own pixels,
and the normal equations are per-match matrix products and solves (tested).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .warping import ImageStack, offset_grid

#: Gauss-Newton stops for a match once its shift update is below this (common-frame pixels).
DEFAULT_TOL_PX = 1e-3
#: singular values of A outside [1 / _MAX_SCALE, _MAX_SCALE] mark a degenerate alignment.
_MAX_SCALE = 2.0
#: gains r1 outside [1 / _MAX_GAIN, _MAX_GAIN] mark a degenerate alignment.
_MAX_GAIN = 5.0

#: ``sampler(rows, A, t, radius)`` -> (n, S, S) values of the search images at the
#: common-frame offsets ``t + A u`` from each match's centre, u on the (S = 2 radius + 1)^2
#: grid of :func:`~.warping.offset_grid`: rows (n,) int64 indices of the matches, A (n, 2, 2)
#: and t (n, 2) float64.
Sampler = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int], torch.Tensor]


@dataclass(frozen=True)
class LSMResult:
    """Output of :func:`lsm_align` (J matches; common-frame pixels).

    Attributes:
        shift: (J, 2) float64 final shift t (x, y) relative to each match's centre.
        sigma: (J, 2) float64 a-posteriori standard deviations of t's x and y.
        sigma_max: (J,) float64 largest semi-axis of t's standard error ellipse (the
            precision along the least determined direction); +inf where the normal matrix
            is singular.
        affine: (J, 2, 2) float64 final A.
        gain, offset: (J,) float64 final r1, r0.
        residual_std: (J,) float64 s0 (intensity units of the inputs).
        converged: (J,) bool: the shift update fell below the tolerance within the
            iterations allowed, and A, the gain and the normal matrix stayed regular.
        iterations: (J,) int64 Gauss-Newton steps taken.
    """

    shift: torch.Tensor
    sigma: torch.Tensor
    sigma_max: torch.Tensor
    affine: torch.Tensor
    gain: torch.Tensor
    offset: torch.Tensor
    residual_std: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor


def lsm_align(
    sampler: Sampler,
    templates: torch.Tensor,
    shift0: torch.Tensor,
    *,
    affine: bool = True,
    max_iterations: int = 10,
    tol_px: float = DEFAULT_TOL_PX,
    max_shift_px: float | None = None,
) -> LSMResult:
    """Align J templates to the search images by Gauss-Newton, each match on its own.

    (Long on purpose: one Gauss-Newton loop whose per-match stop, normal equations and
    precision share their batched tensors; split, each piece would pass them all around.)

    Args:
        sampler: reads the search images (see :data:`Sampler`); must be elementwise per
            match for the result to be batch independent.
        templates: (J, S, S) float reference patches, S = 2r + 1, on the grid
            :func:`~.warping.offset_grid` (r) (row-major, [y, x]).
        shift0: (J, 2) float64 starting shift (e.g. the NCC sub-pixel peak); A starts at
            the identity, (r0, r1) at the values matching the means and standard deviations.
        affine: estimate the 4 affine terms of A (8 parameters); False: shift and radiometry
            only (4), A stays the identity.
        max_iterations: Gauss-Newton steps per match at most.
        tol_px: a match converges once its shift update (max over x, y) is below this.
        max_shift_px: a match whose shift leaves ``shift0`` by more than this stops there,
            not converged (None: no bound).
    Returns:
        :class:`LSMResult` on the device of ``templates``.
    """
    J, S = templates.shape[0], templates.shape[-1]
    if templates.ndim != 3 or templates.shape[1] != S or S % 2 == 0:
        raise ValueError(f"templates must be (J, S, S) with S odd, got {tuple(templates.shape)}")
    if shift0.shape != (J, 2):
        raise ValueError(f"shift0 must be ({J}, 2), got {tuple(shift0.shape)}")
    dev = templates.device
    f64, f32 = torch.float64, torch.float32
    radius = S // 2
    u = offset_grid(radius, dev, f32)  # (P, 2)
    P = u.shape[0]
    n_par = 8 if affine else 4
    p_pad = -(-P // 16) * 16  # float32 row length, a multiple of 64 bytes
    tpl = templates.reshape(J, P).to(f32)
    t = shift0.to(f64).clone()
    A = torch.eye(2, dtype=f64, device=dev).repeat(J, 1, 1)
    r0 = torch.zeros(J, dtype=f64, device=dev)
    r1 = torch.ones(J, dtype=f64, device=dev)
    sigma = torch.full((J, 2), float("inf"), dtype=f64, device=dev)
    sigma_max = torch.full((J,), float("inf"), dtype=f64, device=dev)
    s0 = torch.full((J,), float("nan"), dtype=f64, device=dev)
    converged = torch.zeros(J, dtype=torch.bool, device=dev)
    iters = torch.zeros(J, dtype=torch.int64, device=dev)
    eye_rhs = torch.zeros((1, n_par, 2), dtype=f64, device=dev)
    eye_rhs[0, 0, 0] = eye_rhs[0, 1, 1] = 1.0
    eye_p = torch.eye(n_par, dtype=f64, device=dev)
    rows = torch.arange(J, device=dev)  # the matches still iterating
    for it in range(max_iterations):
        if rows.numel() == 0:
            break
        n = rows.numel()
        Ar, tr = A[rows], t[rows]
        vals = sampler(rows, Ar, tr, radius + 1).to(f32)  # (n, S + 2, S + 2)
        g = vals[:, 1:-1, 1:-1].reshape(n, P)
        f = tpl[rows]
        if it == 0:  # radiometry matching the first patch's mean and spread
            fm, gm = f.mean(dim=1, dtype=f64), g.mean(dim=1, dtype=f64)
            fs = (f - fm[:, None]).square().sum(dim=1, dtype=f64).sqrt()
            gs = (g - gm[:, None]).square().sum(dim=1, dtype=f64).sqrt()
            gain0 = torch.where((gs > 1e-12) & (fs > 1e-12), fs / gs.clamp_min(1e-12),
                                torch.ones_like(gs))
            r1[rows] = gain0
            r0[rows] = fm - gain0 * gm
        a1, a0 = r1[rows], r0[rows]
        a1f = a1.to(f32)[:, None]
        # rows: the p Jacobian columns, then the residual; one batched product gives the
        # normal matrix N, the right-hand side b = J^T e and e^T e
        # each row padded with zeros to a multiple of 64 bytes: every match's matrix then
        # starts equally aligned wherever it sits in the batch, and the batched product
        # takes the same path for it (unaligned rows were seen to round differently)
        Jm = torch.empty((n, n_par + 1, p_pad), dtype=f32, device=dev)
        Jm[:, :, P:] = 0.0
        sx, sy = Jm[:, 0, :P], Jm[:, 1, :P]
        torch.sub(vals[:, 1:-1, 2:], vals[:, 1:-1, :-2], out=sx.view(n, S, S))
        torch.sub(vals[:, 2:, 1:-1], vals[:, :-2, 1:-1], out=sy.view(n, S, S))
        sx.mul_(0.5 * a1f)
        sy.mul_(0.5 * a1f)
        Jm[:, 2, :P] = 1.0
        Jm[:, 3, :P] = g
        if affine:
            torch.mul(sx, u[:, 0], out=Jm[:, 4, :P])
            torch.mul(sx, u[:, 1], out=Jm[:, 5, :P])
            torch.mul(sy, u[:, 0], out=Jm[:, 6, :P])
            torch.mul(sy, u[:, 1], out=Jm[:, 7, :P])
        torch.sub(f, a0.to(f32)[:, None] + a1f * g, out=Jm[:, n_par, :P])  # residuals e
        NN = torch.bmm(Jm, Jm.transpose(1, 2)).to(f64)  # (n, p + 1, p + 1)
        N = NN[:, :n_par, :n_par]
        b = NN[:, :n_par, n_par:]  # (n, p, 1)
        L, info = torch.linalg.cholesky_ex(N)
        ok = info == 0
        L = torch.where(ok[:, None, None], L, eye_p)
        sol = torch.cholesky_solve(torch.cat([b, eye_rhs.expand(n, n_par, 2)], dim=2), L)
        x = sol[:, :, 0]
        var0 = NN[:, n_par, n_par] / (P - n_par)
        d0, d1 = x[:, 0], x[:, 1]
        step = torch.stack([Ar[:, 0, 0] * d0 + Ar[:, 0, 1] * d1,
                            Ar[:, 1, 0] * d0 + Ar[:, 1, 1] * d1], dim=-1)
        step = torch.where(ok[:, None], step, torch.zeros_like(step))
        sg, sm = _shift_sigma(Ar, var0[:, None, None] * sol[:, :2, 1:])
        inf = torch.full_like(sm, float("inf"))
        sigma[rows] = torch.where(ok[:, None], sg, inf[:, None].expand(n, 2))
        sigma_max[rows] = torch.where(ok, sm, inf)
        s0[rows] = var0.sqrt()
        t_new = tr + step
        zero = torch.zeros_like(a1)
        r1_new = a1 + torch.where(ok, x[:, 3], zero)
        a_new = Ar
        if affine:
            D = torch.where(ok[:, None], x[:, 4:8], torch.zeros_like(x[:, 4:8]))
            a_new = torch.stack([
                torch.stack([Ar[:, 0, 0] * (1 + D[:, 0]) + Ar[:, 0, 1] * D[:, 2],
                             Ar[:, 0, 0] * D[:, 1] + Ar[:, 0, 1] * (1 + D[:, 3])], -1),
                torch.stack([Ar[:, 1, 0] * (1 + D[:, 0]) + Ar[:, 1, 1] * D[:, 2],
                             Ar[:, 1, 0] * D[:, 1] + Ar[:, 1, 1] * (1 + D[:, 3])], -1),
            ], dim=1)
        t[rows] = t_new
        A[rows] = a_new
        r0[rows] = a0 + torch.where(ok, x[:, 2], zero)
        r1[rows] = r1_new
        iters[rows] += 1
        regular = ok & _regular(a_new, r1_new)
        small = step.abs().amax(dim=1) < tol_px
        done = ~regular | small
        if max_shift_px is not None:
            done |= (t_new - shift0[rows].to(f64)).abs().amax(dim=1) > max_shift_px
        converged[rows] = regular & small
        rows = rows[~done]
    return LSMResult(shift=t, sigma=sigma, sigma_max=sigma_max, affine=A, gain=r1, offset=r0,
                     residual_std=s0, converged=converged, iterations=iters)


def _shift_sigma(A: torch.Tensor, C: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Standard deviations (n, 2) of t = A d and the largest semi-axis (n,) of its error
    ellipse, from the covariance C (n, 2, 2) of d (elementwise: A C A^T)."""
    AC = A[:, :, 0, None] * C[:, None, 0, :] + A[:, :, 1, None] * C[:, None, 1, :]
    cxx = AC[:, 0, 0] * A[:, 0, 0] + AC[:, 0, 1] * A[:, 0, 1]
    cyy = AC[:, 1, 0] * A[:, 1, 0] + AC[:, 1, 1] * A[:, 1, 1]
    cxy = AC[:, 0, 0] * A[:, 1, 0] + AC[:, 0, 1] * A[:, 1, 1]
    lam = 0.5 * (cxx + cyy) + torch.sqrt((0.5 * (cxx - cyy)).square() + cxy.square())
    return torch.stack([cxx, cyy], -1).clamp_min(0).sqrt(), lam.clamp_min(0).sqrt()


def _regular(A: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """(n,) bool: A's singular values within [1/_MAX_SCALE, _MAX_SCALE] and its determinant
    positive (no reflection), the gain within [1/_MAX_GAIN, _MAX_GAIN]."""
    a, b, c, d = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
    det = a * d - b * c
    fro2 = a * a + b * b + c * c + d * d
    disc = (fro2.square() - 4 * det.square()).clamp_min(0).sqrt()
    smax2, smin2 = 0.5 * (fro2 + disc), 0.5 * (fro2 - disc)
    return ((det > 0) & (smax2 <= _MAX_SCALE**2) & (smin2 >= _MAX_SCALE**-2)
            & (gain >= 1 / _MAX_GAIN) & (gain <= _MAX_GAIN))


def frame_sampler(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    mode: str = "bicubic",
) -> Sampler:
    """A :data:`Sampler` of the rectified search images: match j reads its image at
    ``H_inv[j] (centres[j] + t + A u)``.

    The map from the grid ``u`` to ``grid_sample`` coordinates is composed per match in
    float64 (elementwise), then evaluated in float32 once per grid column and row.

    Args:
        image: (H, W) float32, or an :class:`~.warping.ImageStack` with one image per match.
        H_inv: (J, 3, 3) float64, common frame -> image pixels (integer = pixel centre).
        centres: (J, 2) float64 common-frame centre of each match.
        mode: ``grid_sample`` interpolation, "bicubic" or "bilinear" (for comparison).
    """

    def sample(rows: torch.Tensor, A: torch.Tensor, t: torch.Tensor, radius: int) -> torch.Tensor:
        n = rows.numel()
        if isinstance(image, ImageStack):
            sub = image.rows(rows)
            size, idx, ims = sub.sizes, sub.index, sub.images
        else:
            size = torch.tensor([[image.shape[1], image.shape[0]]], dtype=torch.float64,
                                device=t.device).expand(n, 2)
            idx, ims = None, (image,)
        # M = S H_inv [[A, c + t], [0, 0, 1]] with S pixels -> grid units (align_corners)
        H = H_inv[rows]
        c = centres[rows] + t
        sc = 2.0 / (size - 1.0).clamp_min(1.0)
        Sm = torch.zeros((n, 3, 3), dtype=torch.float64, device=t.device)
        Sm[:, 0, 0], Sm[:, 1, 1], Sm[:, 0, 2], Sm[:, 1, 2], Sm[:, 2, 2] = sc[:, 0], sc[:, 1], -1.0, -1.0, 1.0
        K = torch.zeros((n, 3, 3), dtype=torch.float64, device=t.device)
        K[:, :2, :2], K[:, :2, 2], K[:, 2, 2] = A, c, 1.0
        M = _mul3(Sm, _mul3(H, K)).to(torch.float32)
        side = 2 * radius + 1
        ax = torch.arange(-radius, radius + 1, dtype=torch.float32, device=t.device)
        m = M[:, :, :, None]  # (n, 3, 3, 1)
        v = (m[:, :, 0] * ax)[:, :, None, :] + (m[:, :, 1] * ax)[:, :, :, None]
        v += m[:, :, 2, :, None]  # (n, 3, side_y, side_x)
        v = v[:, :2] / v[:, 2:].clamp_min(1e-6)
        grid = v.view(n, 2, side * side).transpose(1, 2)  # (n, Q, 2)
        if idx is None:
            out = F.grid_sample(ims[0][None, None], grid[None], mode=mode,
                                padding_mode="border", align_corners=True)[0, 0]
            return out.view(n, side, side)
        out = torch.empty((n, side * side), dtype=torch.float32, device=t.device)
        for k in torch.unique(idx).tolist():
            sel = torch.nonzero(idx == k)[:, 0]
            out[sel] = F.grid_sample(ims[k][None, None], grid[sel][None], mode=mode,
                                     padding_mode="border", align_corners=True)[0, 0]
        return out.view(n, side, side)

    return sample


def _mul3(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """(n, 3, 3) products X Y, elementwise (no batched GEMM)."""
    return (X[:, :, 0, None] * Y[:, None, 0, :] + X[:, :, 1, None] * Y[:, None, 1, :]
            + X[:, :, 2, None] * Y[:, None, 2, :])
