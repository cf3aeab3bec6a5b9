"""Least-squares matching (LSM, Gruen 1985): batched Gauss-Newton alignment of patches.

Per match the template ``f(u)`` is aligned by ``f(u) + e(u) = r0 + r1 G(t + A u)`` (affine ``A``,
shift ``t`` in common-frame pixels, radiometry ``r0``, ``r1``), forward-compositional, with bicubic
reads (bilinear ones bias values towards pixel centres). The CUDA path and the reference of the
compiled CPU kernel (:mod:`.kernel`); a match's result never depends on the others."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from ..warping import ImageStack, offset_grid
from .result import DEFAULT_TOL_PX, MAX_GAIN, MAX_SCALE, LSMResult

#: the 4 blur taps (i, j) of a blurred read: the sample at t + i step_x + j step_y.
_BLUR_TAPS = ((-1, -1), (1, -1), (-1, 1), (1, 1))

#: ``sampler(rows, A, t, radius)`` -> (n, S, S) values of the search images at the
#: common-frame offsets ``t + A u`` from each match's centre, u on the (S = 2 radius + 1)^2
#: grid of :func:`~..warping.offset_grid`: rows (n,) int64 indices of the matches, A (n, 2, 2)
#: and t (n, 2) float64.
Sampler = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int], torch.Tensor]


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

    ``sampler`` reads the search images (elementwise per match); ``templates`` ``(J, S, S)``, S = 2r
    + 1, row-major; ``shift0`` ``(J, 2)`` float64 start (A = I, radiometry from the means and
    spreads). ``tol_px``: stop once the shift update is below it; ``max_shift_px``: stop, not
    converged, beyond it. Returns :class:`LSMResult` on the templates' device."""
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
    out = _start_outputs(shift0.to(f64))
    # the state of the matches still iterating (rows ``act`` of the outputs), compacted as
    # matches stop: every per-iteration operation runs on the active matches only
    act = torch.arange(J, device=dev)
    tpl = templates.reshape(J, P).to(f32)
    start = shift0.to(f64)
    t = start.clone()
    A = torch.eye(2, dtype=f64, device=dev).repeat(J, 1, 1)
    eye_rhs = torch.zeros((1, n_par, 2), dtype=f64, device=dev)
    eye_rhs[0, 0, 0] = eye_rhs[0, 1, 1] = 1.0
    eye_p = torch.eye(n_par, dtype=f64, device=dev)
    eye2 = torch.eye(2, dtype=f64, device=dev)
    r0 = r1 = torch.zeros(0, dtype=f64, device=dev)
    jm_buf = torch.zeros((J, n_par + 1, p_pad), dtype=f32, device=dev)
    jm_buf[:, 2, :P] = 1.0
    for it in range(max_iterations):
        n = act.numel()
        if n == 0:
            break
        vals = sampler(act, A, t, radius + 1).to(f32)  # (n, S + 2, S + 2)
        Jm = jm_buf[:n]
        Jm[:, 3, :P].view(n, S, S).copy_(vals[:, 1:-1, 1:-1])
        g = Jm[:, 3, :P]  # the patch, row 3 of the Jacobian (the gain's column)
        if it == 0:  # radiometry matching the first patch's mean and spread
            r0, r1 = _initial_radiometry(tpl, g)
        r1f = r1.to(f32)[:, None]
        # rows: the p Jacobian columns, then the residual; one batched product gives the
        # normal matrix N, the right-hand side b = J^T e and e^T e
        # each row padded with zeros to a multiple of 64 bytes: every match's matrix then
        # starts equally aligned wherever it sits in the batch, and the batched product
        # takes the same path for it (unaligned rows were seen to round differently)
        # (one buffer for all iterations: the padding and the row of ones are written once)
        sxy = Jm[:, :2, :P].view(n, 2, S, S)
        torch.sub(vals[:, 1:-1, 2:], vals[:, 1:-1, :-2], out=sxy[:, 0])
        torch.sub(vals[:, 2:, 1:-1], vals[:, :-2, 1:-1], out=sxy[:, 1])
        sxy.mul_((0.5 * r1f)[:, :, None, None])
        if affine:
            torch.mul(Jm[:, :2, None, :P], u.T[None, None], out=Jm[:, 4:8, :P].view(n, 2, 2, P))
        torch.sub(tpl, r0.to(f32)[:, None] + r1f * g, out=Jm[:, n_par, :P])  # residuals e
        NN = torch.bmm(Jm, Jm.transpose(1, 2)).to(f64)  # (n, p + 1, p + 1)
        L, info = torch.linalg.cholesky_ex(NN[:, :n_par, :n_par])
        ok = info == 0
        L = torch.where(ok[:, None, None], L, eye_p)
        sol = torch.cholesky_solve(torch.cat([NN[:, :n_par, n_par:], eye_rhs.expand(n, n_par, 2)],
                                             dim=2), L)
        x = torch.where(ok[:, None], sol[:, :, 0], 0.0)
        var0 = NN[:, n_par, n_par] / (P - n_par)
        step = (A * x[:, None, :2]).sum(dim=2)  # A d
        sg, sm = _shift_sigma(A, var0[:, None, None] * sol[:, :2, 1:])
        sg = torch.where(ok[:, None], sg, float("inf"))
        sm = torch.where(ok, sm, float("inf"))
        t = t + step
        r0 = r0 + x[:, 2]
        r1 = r1 + x[:, 3]
        if affine:  # A (I + D)
            E = eye2 + x[:, 4:8].view(n, 2, 2)
            A = (A[:, :, :, None] * E[:, None, :, :]).sum(dim=2)
        regular = ok & _regular(A, r1)
        small = step.abs().amax(dim=1) < tol_px
        done = ~regular | small
        if max_shift_px is not None:
            done |= (t - start).abs().amax(dim=1) > max_shift_px
        if it == max_iterations - 1:
            done = torch.ones_like(done)
        fin = torch.nonzero(done)[:, 0]
        _write_outputs(out, act[fin], t[fin], sg[fin], sm[fin], A[fin], r1[fin], r0[fin],
                       var0[fin].sqrt(), (regular & small)[fin], it + 1)
        if fin.numel() < n:
            keep = torch.nonzero(~done)[:, 0]
            act, tpl, start, t, A, r0, r1 = (v[keep] for v in (act, tpl, start, t, A, r0, r1))
        else:
            act = act[:0]
    return out


def _start_outputs(shift0: torch.Tensor) -> LSMResult:
    """The result of J matches before any step (shift0, A = I, r0 = 0, r1 = 1, not converged)."""
    J, dev, f64 = shift0.shape[0], shift0.device, torch.float64
    return LSMResult(shift=shift0.clone(),
                     sigma=torch.full((J, 2), float("inf"), dtype=f64, device=dev),
                     sigma_max=torch.full((J,), float("inf"), dtype=f64, device=dev),
                     affine=torch.eye(2, dtype=f64, device=dev).repeat(J, 1, 1),
                     gain=torch.ones(J, dtype=f64, device=dev),
                     offset=torch.zeros(J, dtype=f64, device=dev),
                     residual_std=torch.full((J,), float("nan"), dtype=f64, device=dev),
                     converged=torch.zeros(J, dtype=torch.bool, device=dev),
                     iterations=torch.zeros(J, dtype=torch.int64, device=dev))


def _write_outputs(out: LSMResult, rows: torch.Tensor, t: torch.Tensor, sigma: torch.Tensor,
                   sigma_max: torch.Tensor, A: torch.Tensor, gain: torch.Tensor, offset: torch.Tensor,
                   s0: torch.Tensor, converged: torch.Tensor, iterations: int) -> None:
    out.shift[rows], out.sigma[rows], out.sigma_max[rows] = t, sigma, sigma_max
    out.affine[rows], out.gain[rows], out.offset[rows] = A, gain, offset
    out.residual_std[rows], out.converged[rows] = s0, converged
    out.iterations[rows] = iterations


def _initial_radiometry(f: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(r0, r1)`` ``(n,)`` matching g's mean and spread to f's (r1 = 1 where a patch is flat)."""
    fm, gm = f.mean(dim=1, dtype=torch.float64), g.mean(dim=1, dtype=torch.float64)
    fs = (f - fm[:, None]).square().sum(dim=1, dtype=torch.float64).sqrt()
    gs = (g - gm[:, None]).square().sum(dim=1, dtype=torch.float64).sqrt()
    gain0 = torch.where((gs > 1e-12) & (fs > 1e-12), fs / gs.clamp_min(1e-12), torch.ones_like(gs))
    return fm - gain0 * gm, gain0


def _shift_sigma(A: torch.Tensor, C: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Standard deviations ``(n, 2)`` of ``t = A d`` and the largest semi-axis ``(n,)`` of its ellipse."""
    AC = (A[:, :, :, None] * C[:, None, :, :]).sum(dim=2)  # AC[i, j] = A[i, 0] C[0, j] + A[i, 1] C[1, j]
    cc = (AC * A).sum(dim=2)  # (cxx, cyy): AC[i, 0] A[i, 0] + AC[i, 1] A[i, 1]
    cxx, cyy = cc.unbind(dim=1)
    cxy = (AC[:, 0] * A[:, 1]).sum(dim=1)
    lam = 0.5 * (cxx + cyy) + torch.sqrt((0.5 * (cxx - cyy)).square() + cxy.square())
    return cc.clamp_min(0).sqrt(), lam.clamp_min(0).sqrt()


def _regular(A: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """``(n,)`` bool: A's singular values within ``MAX_SCALE``, no reflection, gain within ``MAX_GAIN``."""
    a, b, c, d = A.reshape(-1, 4).unbind(dim=1)
    det = a * d - b * c
    fro2 = a * a + b * b + c * c + d * d
    disc = (fro2.square() - 4 * det.square()).clamp_min(0).sqrt()
    smax2, smin2 = 0.5 * (fro2 + disc), 0.5 * (fro2 - disc)
    return ((det > 0) & (smax2 <= MAX_SCALE**2) & (smin2 >= MAX_SCALE**-2)
            & (gain >= 1 / MAX_GAIN) & (gain <= MAX_GAIN))


def frame_sampler(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    blur: tuple[torch.Tensor, torch.Tensor] | None = None,
    blur_px: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> Sampler:
    """A :data:`Sampler` of the rectified search images: match j reads ``H_inv[j] (centres[j] + t +
    A u)``.

    ``H_inv`` ``(J, 3, 3)`` frame -> image pixels, ``centres`` ``(J, 2)``. ``blur``: matches with
    ``on`` read the mean of 4 samples at ``t + step[j] o``, o in {-1, 1}^2 (frame offsets);
    ``blur_px``: the same along the image's own axes by ``sigma[j]`` pixels. Not both."""
    if blur is not None and blur_px is not None:
        raise ValueError("frame_sampler takes blur or blur_px, not both")

    J = centres.shape[0]
    dev = centres.device
    f64 = torch.float64
    if isinstance(image, ImageStack):
        size, index, ims = image.sizes, image.index, image.images
    else:
        size = torch.tensor([[image.shape[1], image.shape[0]]], dtype=f64, device=dev).expand(J, 2)
        index, ims = None, (image,)
    # B = S H_inv per match, S pixels -> grid units (align_corners); then
    # M = B [[A, c + t], [0, 0, 1]] for each call's A and t
    sc = 2.0 / (size - 1.0).clamp_min(1.0)
    Sm = torch.zeros((J, 3, 3), dtype=f64, device=dev)
    Sm[:, 0, 0], Sm[:, 1, 1], Sm[:, 0, 2], Sm[:, 1, 2], Sm[:, 2, 2] = sc[:, 0], sc[:, 1], -1.0, -1.0, 1.0
    B = _mul3(Sm, H_inv.to(f64))

    def sample(rows: torch.Tensor, A: torch.Tensor, t: torch.Tensor, radius: int) -> torch.Tensor:
        spec = blur if blur is not None else blur_px
        if spec is None:
            return read(rows, A, t, radius)
        on = spec[0][rows]
        if not bool(on.any()):
            return read(rows, A, t, radius)
        sel, keep = torch.nonzero(on)[:, 0], torch.nonzero(~on)[:, 0]
        nb, nk, side = sel.numel(), keep.numel(), 2 * radius + 1
        nt = len(_BLUR_TAPS)
        rows4 = torch.cat([rows[keep], rows[sel].repeat_interleave(nt)])
        A4 = torch.cat([A[keep], A[sel].repeat_interleave(nt, dim=0)])
        if blur is not None:
            st, t_s = blur[1][rows[sel]], t[sel]
            t4 = torch.stack([t_s + i * st[:, :, 0] + j * st[:, :, 1] for i, j in _BLUR_TAPS], dim=1)
            v = read(rows4, A4, torch.cat([t[keep], t4.view(-1, 2)]), radius)
        else:
            sg = spec[1][rows[sel]].to(f64)
            o4 = torch.stack([torch.stack([i * sg, j * sg], dim=1) for i, j in _BLUR_TAPS], dim=1)
            off = torch.cat([torch.zeros((nk, 2), dtype=f64, device=dev), o4.view(-1, 2)])
            v = read(rows4, A4, torch.cat([t[keep], t[sel].repeat_interleave(nt, dim=0)]), radius, off)
        out = torch.empty((rows.numel(), side, side), dtype=torch.float32, device=t.device)
        out[keep] = v[:nk]
        taps = v[nk:].view(nb, len(_BLUR_TAPS), side, side)
        acc = taps[:, 0] + taps[:, 1]
        for k in range(2, len(_BLUR_TAPS)):
            acc += taps[:, k]
        out[sel] = acc / len(_BLUR_TAPS)
        return out

    def read(rows: torch.Tensor, A: torch.Tensor, t: torch.Tensor, radius: int,
             off: torch.Tensor | None = None) -> torch.Tensor:
        """``(n, S, S)`` samples; ``off`` ``(n, 2)`` image pixels added to every position, or None."""
        n = rows.numel()
        Br = B[rows]
        c = centres[rows] + t
        # M[:, :, :2] = B[:, :, :2] A, M[:, :, 2] = B[:, :, :2] c + B[:, :, 2] (elementwise)
        M = torch.cat([(Br[:, :, :2, None] * A[:, None]).sum(dim=2),
                       ((Br[:, :, :2] * c[:, None]).sum(dim=2) + Br[:, :, 2])[:, :, None]],
                      dim=2).to(torch.float32)
        side = 2 * radius + 1
        # the image offsets in grid units (float32, added to the float32 grid)
        offg = None if off is None else (off * sc[rows]).to(torch.float32)[:, None, :]
        if index is None:
            return _grid_sample(ims[0], _shifted(_frame_grid(M, radius), offg)).view(n, side, side)
        idx = index[rows]
        counts = torch.bincount(idx, minlength=len(ims)).tolist()
        if n and max(counts) == n:  # one image
            return _grid_sample(ims[counts.index(n)], _shifted(_frame_grid(M, radius), offg)).view(n, side, side)
        order = torch.argsort(idx, stable=True)  # the matches grouped by image
        grid = _shifted(_frame_grid(M[order], radius), None if offg is None else offg[order])
        parts, lo = [], 0
        for k, cnt in enumerate(counts):
            if cnt:
                parts.append(_grid_sample(ims[k], grid[lo:lo + cnt]))
                lo += cnt
        out = torch.empty((n, side * side), dtype=torch.float32, device=t.device)
        out[order] = torch.cat(parts)
        return out.view(n, side, side)

    return sample


def _frame_grid(M: torch.Tensor, radius: int) -> torch.Tensor:
    """Grid coordinates ``(n, Q, 2)`` float32 of the offsets under the maps ``M`` ``(n, 3, 3)``, elementwise."""
    side = 2 * radius + 1
    ax = torch.arange(-radius, radius + 1, dtype=torch.float32, device=M.device)
    m = M[:, :, :, None]  # (n, 3, 3, 1)
    v = (m[:, :, 0] * ax)[:, :, None, :] + (m[:, :, 1] * ax)[:, :, :, None]  # (n, 3, S_y, S_x)
    v += m[:, :, 2, :, None]
    out = torch.empty((M.shape[0], side, side, 2), dtype=torch.float32, device=M.device)
    w = v[:, 2].clamp_min_(1e-6)
    torch.div(v[:, 0], w, out=out[..., 0])
    torch.div(v[:, 1], w, out=out[..., 1])
    return out.view(-1, side * side, 2)


def _shifted(grid: torch.Tensor, off: torch.Tensor | None) -> torch.Tensor:
    return grid if off is None else grid.add_(off)


def _grid_sample(image: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bicubic samples ``(n, Q)`` of one image at ``grid`` (``align_corners=True``, border outside)."""
    return F.grid_sample(image[None, None], grid[None], mode="bicubic", padding_mode="border",
                         align_corners=True)[0, 0]


def _mul3(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """(n, 3, 3) products X Y, elementwise (no batched GEMM)."""
    return (X[:, :, 0, None] * Y[:, None, 0, :] + X[:, :, 1, None] * Y[:, None, 1, :]
            + X[:, :, 2, None] * Y[:, None, 2, :])
