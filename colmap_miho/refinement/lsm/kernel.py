"""Compiled (numba) least-squares matching: :func:`lsm_frames` does on CPU tensors what
:func:`.align.frame_sampler` and :func:`.align.lsm_align` do, one fused loop per match, so an
iteration costs its arithmetic; results differ from torch's at float rounding only."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ...compiled import CONTRACT, REASSOC, Kernels, jit, jit_helpers
from ...validation import MAX_BLUR_PX, MAX_WINDOW_RADIUS_PX
from ..warping import ImageStack, image_arrays
from .result import DEFAULT_TOL_PX, MAX_GAIN, MAX_SCALE, LSMResult

#: Keys' cubic convolution parameter of ``grid_sample``'s bicubic mode.
KEYS_A = -0.75
#: taps per axis of a smoothed read in fixed loops (blurs up to 1 px); wider ones loop on
#: their own span.
_FIXED_SPAN = 6


def _cubic(t: float, a: float) -> tuple[float, float, float, float]:
    """The cubic convolution weights at taps -1, 0, 1, 2 for a fractional position ``t``."""
    a2, a3, a4, a5, a8 = a + 2.0, a + 3.0, 4.0 * a, 5.0 * a, 8.0 * a
    s = t + 1.0
    w0 = ((a * s - a5) * s + a8) * s - a4
    w1 = (a2 * t - a3) * t * t + 1.0
    s = 1.0 - t
    w2 = (a2 * s - a3) * s * s + 1.0
    s = 2.0 - t
    w3 = ((a * s - a5) * s + a8) * s - a4
    return w0, w1, w2, w3


def _compose(H, cx: float, cy: float, a00: float, a01: float, a10: float, a11: float
             ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """Row-major entries of ``M = H [[A, c], [0, 0, 1]]``: the image's homogeneous coordinates of offsets u."""
    m00 = H[0, 0] * a00 + H[0, 1] * a10
    m01 = H[0, 0] * a01 + H[0, 1] * a11
    m02 = H[0, 0] * cx + H[0, 1] * cy + H[0, 2]
    m10 = H[1, 0] * a00 + H[1, 1] * a10
    m11 = H[1, 0] * a01 + H[1, 1] * a11
    m12 = H[1, 0] * cx + H[1, 1] * cy + H[1, 2]
    m20 = H[2, 0] * a00 + H[2, 1] * a10
    m21 = H[2, 0] * a01 + H[2, 1] * a11
    m22 = H[2, 0] * cx + H[2, 1] * cy + H[2, 2]
    return m00, m01, m02, m10, m11, m12, m20, m21, m22


def _read(img, H, cx: float, cy: float, a00: float, a01: float, a10: float, a11: float,
          radius: int, a: float, out, add: bool, wts, taps) -> None:
    """``out`` ``(S, S)`` ``[y, x]``: ``img`` read bicubically at ``H (c + A u)`` (border clamped),
    added when ``add``; ``wts`` and ``taps`` are work space."""
    h, w = img.shape
    # M = H [[A, c], [0, 0, 1]]: the image's homogeneous coordinates of u
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = _compose(H, cx, cy, a00, a01, a10, a11)
    side = 2 * radius + 1
    wx, wy, xi, yi = wts[0], wts[1], taps[0], taps[1]
    # positions beyond 2 pixels outside the image read its border (all 4 taps clamped) as
    # at 2 pixels: clamping them first keeps the integer conversion in range
    fw, fh = w + 1.0, h + 1.0
    for iy in range(side):
        uy = float(iy - radius)
        bx, by, bw = m01 * uy + m02, m11 * uy + m12, m21 * uy + m22
        for ix in range(side):
            ux = float(ix - radius)
            hw = max(m20 * ux + bw, 1e-6)
            x = min(max((m00 * ux + bx) / hw, -2.0), fw)
            y = min(max((m10 * ux + by) / hw, -2.0), fh)
            fx, fy = np.floor(x), np.floor(y)
            # the cubic convolution kernel (parameter a) at the taps -1, 0, 1, 2 from the floor
            wx[0, ix], wx[1, ix], wx[2, ix], wx[3, ix] = _cubic(x - fx, a)
            wy[0, ix], wy[1, ix], wy[2, ix], wy[3, ix] = _cubic(y - fy, a)
            xi[ix] = int(fx) - 1
            yi[ix] = int(fy) - 1
        for ix in range(side):
            x0, y0 = xi[ix], yi[ix]
            w0, w1, w2, w3 = wx[0, ix], wx[1, ix], wx[2, ix], wx[3, ix]
            v = 0.0
            if x0 >= 0 and x0 <= w - 4 and y0 >= 0 and y0 <= h - 4:
                for k in range(4):
                    r = img[y0 + k]
                    v += (r[x0] * w0 + r[x0 + 1] * w1 + r[x0 + 2] * w2 + r[x0 + 3] * w3) * wy[k, ix]
            else:
                c0, c1 = min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)
                c2, c3 = min(max(x0 + 2, 0), w - 1), min(max(x0 + 3, 0), w - 1)
                for k in range(4):
                    r = img[min(max(y0 + k, 0), h - 1)]
                    v += (r[c0] * w0 + r[c1] * w1 + r[c2] * w2 + r[c3] * w3) * wy[k, ix]
            if add:
                out[iy, ix] += v
            else:
                out[iy, ix] = v


def _dot(x, y) -> float:
    """Dot product of x and y, reassociated but in the same order for every pair of length n."""
    acc = 0.0
    for k in range(x.shape[0]):
        acc += x[k] * y[k]
    return acc


def _smoothed(img, H, cx: float, cy: float, a00: float, a01: float, a10: float, a11: float,
              radius: int, a: float, sigma: float, out, cw, base) -> None:
    """:func:`_read` smoothed: the mean of 4 bicubic reads at ``(x +- sigma, y +- sigma)`` as one
    read with merged taps (the mean is separable); ``cw`` and ``base`` are work space."""
    h, w = img.shape
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = _compose(H, cx, cy, a00, a01, a10, a11)
    side = 2 * radius + 1
    cwx, cwy = cw[0], cw[1]
    fw, fh = w + 1.0, h + 1.0
    for iy in range(side):
        uy = float(iy - radius)
        bx, by, bw = m01 * uy + m02, m11 * uy + m12, m21 * uy + m22
        for ix in range(side):
            ux = float(ix - radius)
            hw = max(m20 * ux + bw, 1e-6)
            px = (m00 * ux + bx) / hw
            py = (m10 * ux + by) / hw
            base[0, ix], base[2, ix] = _merged(px, sigma, fw, a, cwx, ix)
            base[1, ix], base[3, ix] = _merged(py, sigma, fh, a, cwy, ix)
        for ix in range(side):
            x0, y0, nx, ny = base[0, ix], base[1, ix], base[2, ix], base[3, ix]
            v = 0.0
            inside = x0 >= 0 and x0 + _FIXED_SPAN <= w and y0 >= 0 and y0 + _FIXED_SPAN <= h
            if inside and nx <= 5 and ny <= 5:
                # the common cases in fixed loops: 5 x 5 taps (blurs up to 0.5 px) ...
                for r in range(5):
                    row = img[y0 + r]
                    acc = 0.0
                    for c in range(5):
                        acc += row[x0 + c] * cwx[ix, c]
                    v += acc * cwy[ix, r]
            elif inside and nx <= _FIXED_SPAN and ny <= _FIXED_SPAN:
                # ... and 6 x 6 (up to 1 px); zero weights past the span
                for r in range(_FIXED_SPAN):
                    row = img[y0 + r]
                    acc = 0.0
                    for c in range(_FIXED_SPAN):
                        acc += row[x0 + c] * cwx[ix, c]
                    v += acc * cwy[ix, r]
            else:
                for r in range(ny):
                    row = img[min(max(y0 + r, 0), h - 1)]
                    acc = 0.0
                    for c in range(nx):
                        acc += row[min(max(x0 + c, 0), w - 1)] * cwx[ix, c]
                    v += acc * cwy[ix, r]
            out[iy, ix] = v


def _merged(p: float, sigma: float, lim: float, a: float, wv, ix: int) -> tuple[int, int]:
    """Half the sum of one axis' cubic weights at ``p - sigma`` and ``p + sigma`` into ``wv[ix]``;
    returns (first tap, n)."""
    xa = min(max(p - sigma, -2.0), lim)
    xb = min(max(p + sigma, -2.0), lim)
    fa, fb = np.floor(xa), np.floor(xb)
    k = int(fb - fa)
    for c in range(4, max(k + 4, _FIXED_SPAN)):
        wv[ix, c] = 0.0
    w0, w1, w2, w3 = _cubic(xa - fa, a)
    wv[ix, 0] = 0.5 * w0
    wv[ix, 1] = 0.5 * w1
    wv[ix, 2] = 0.5 * w2
    wv[ix, 3] = 0.5 * w3
    w0, w1, w2, w3 = _cubic(xb - fb, a)
    wv[ix, k] += 0.5 * w0
    wv[ix, k + 1] += 0.5 * w1
    wv[ix, k + 2] += 0.5 * w2
    wv[ix, k + 3] += 0.5 * w3
    return int(fa) - 1, k + 4


def _read_blurred(img, H, cx: float, cy: float, a00: float, a01: float, a10: float, a11: float,
                  radius: int, a: float, on: bool, sigma: float, out, wts, taps, cw, base) -> None:
    if on:
        _smoothed(img, H, cx, cy, a00, a01, a10, a11, radius, a, sigma, out, cw, base)
    else:
        _read(img, H, cx, cy, a00, a01, a10, a11, radius, a, out, False, wts, taps)


def _lsm_matches(img_f, img_m, rows, H_f, c_f, H_m, c_m, on_f, sigma_f, on_m, sigma_m, shift0,
                 radius: int, affine: bool, max_iterations: int, tol: float, max_shift: float,
                 a: float, max_scale: float, max_gain: float,
                 shift, sigma, sigma_max, A_out, gain, offset, s0_out, converged, iterations):
    """The LSM of the matches ``rows``, written into the ``(J, ...)`` output arrays."""
    side = 2 * radius + 1
    P = side * side
    npar = 8 if affine else 4
    tpl = np.empty((side, side))
    vals = np.empty((side + 2, side + 2))
    N = np.zeros((npar + 1, npar + 1))
    L = np.zeros((npar, npar))
    Jm = np.ones((npar + 1, P))
    sol = np.zeros((3, npar))
    wts = np.empty((2, 4, side + 2))
    taps = np.empty((2, side + 2), np.int64)
    # the merged taps of smoothed reads: at most 5 + 2 sigma per axis
    sg_max = 0.0
    for q in range(rows.shape[0]):
        j = rows[q]
        sg_max = max(sg_max, sigma_f[j] if on_f[j] else 0.0, sigma_m[j] if on_m[j] else 0.0)
    cw = np.empty((2, side + 2, max(int(2.0 * sg_max) + 6, _FIXED_SPAN)))
    base = np.empty((4, side + 2), np.int64)
    for q in range(rows.shape[0]):
        j = rows[q]
        cxf, cyf = c_f[j, 0], c_f[j, 1]
        _read_blurred(img_f, H_f[j], cxf, cyf, 1.0, 0.0, 0.0, 1.0, radius, a, on_f[j], sigma_f[j], tpl, wts, taps, cw,
                      base)
        sx, sy = shift0[j, 0], shift0[j, 1]
        tx, ty = sx, sy
        a00, a01, a10, a11 = 1.0, 0.0, 0.0, 1.0
        r0 = 0.0
        r1 = 1.0
        for it in range(max_iterations):
            _read_blurred(img_m, H_m[j], c_m[j, 0] + tx, c_m[j, 1] + ty, a00, a01, a10, a11,
                          radius + 1, a, on_m[j], sigma_m[j], vals, wts, taps, cw, base)
            if it == 0:  # radiometry matching the first patch's mean and spread
                fm = 0.0
                gm = 0.0
                for iy in range(side):
                    for ix in range(side):
                        fm += tpl[iy, ix]
                        gm += vals[iy + 1, ix + 1]
                fm /= P
                gm /= P
                fs = 0.0
                gs = 0.0
                for iy in range(side):
                    for ix in range(side):
                        fs += (tpl[iy, ix] - fm) ** 2
                        gs += (vals[iy + 1, ix + 1] - gm) ** 2
                fs, gs = math.sqrt(fs), math.sqrt(gs)
                r1 = fs / gs if (gs > 1e-12 and fs > 1e-12) else 1.0
                r0 = fm - r1 * gm
            # the Jacobian's columns (gx, gy, 1, g, gx ux, gx uy, gy ux, gy uy) and the
            # residual e as rows of Jm, then the normal matrix N = [J e]^T [J e] (lower
            # triangle) by dot products
            hr = 0.5 * r1
            for iy in range(side):
                uy = float(iy - radius)
                for ix in range(side):
                    ux = float(ix - radius)
                    q = iy * side + ix
                    g = vals[iy + 1, ix + 1]
                    gx = hr * (vals[iy + 1, ix + 2] - vals[iy + 1, ix])
                    gy = hr * (vals[iy + 2, ix + 1] - vals[iy, ix + 1])
                    Jm[0, q] = gx
                    Jm[1, q] = gy
                    Jm[3, q] = g
                    if affine:
                        Jm[4, q] = gx * ux
                        Jm[5, q] = gx * uy
                        Jm[6, q] = gy * ux
                        Jm[7, q] = gy * uy
                    Jm[npar, q] = tpl[iy, ix] - (r0 + r1 * g)
            for r in range(npar + 1):
                for c in range(r + 1):
                    N[r, c] = _dot(Jm[r], Jm[c])
            # Cholesky N[:p, :p] = L L^T; a non-positive pivot: singular (ok = False)
            ok = True
            for r in range(npar):
                for c in range(r + 1):
                    s = N[r, c]
                    for k in range(c):
                        s -= L[r, k] * L[c, k]
                    if r == c:
                        if not s > 0.0:
                            ok = False
                            break
                        L[r, r] = math.sqrt(s)
                    else:
                        L[r, c] = s / L[c, c]
                if not ok:
                    break
            var0 = N[npar, npar] / (P - npar)
            dx = dy = 0.0
            sg_x = sg_y = sm = math.inf
            if ok:
                # right-hand sides: b = J^T e, and the unit vectors e0, e1 (the shift's covariance)
                for k in range(npar):
                    sol[0, k] = N[npar, k]
                    sol[1, k] = 1.0 if k == 0 else 0.0
                    sol[2, k] = 1.0 if k == 1 else 0.0
                for m in range(3):
                    for r in range(npar):  # L y = rhs
                        s = sol[m, r]
                        for k in range(r):
                            s -= L[r, k] * sol[m, k]
                        sol[m, r] = s / L[r, r]
                    for r in range(npar - 1, -1, -1):  # L^T x = y
                        s = sol[m, r]
                        for k in range(r + 1, npar):
                            s -= L[k, r] * sol[m, k]
                        sol[m, r] = s / L[r, r]
                dx, dy = sol[0, 0], sol[0, 1]
                # covariance of t = A d: A C A^T, C = var0 (N^-1)_dd
                c00, c01 = var0 * sol[1, 0], var0 * sol[2, 0]
                c10, c11 = var0 * sol[1, 1], var0 * sol[2, 1]
                ac00 = a00 * c00 + a01 * c10
                ac01 = a00 * c01 + a01 * c11
                ac10 = a10 * c00 + a11 * c10
                ac11 = a10 * c01 + a11 * c11
                cxx = ac00 * a00 + ac01 * a01
                cyy = ac10 * a10 + ac11 * a11
                cxy = ac00 * a10 + ac01 * a11
                lam = 0.5 * (cxx + cyy) + math.sqrt((0.5 * (cxx - cyy)) ** 2 + cxy * cxy)
                sg_x, sg_y = math.sqrt(max(cxx, 0.0)), math.sqrt(max(cyy, 0.0))
                sm = math.sqrt(max(lam, 0.0))
            step_x = a00 * dx + a01 * dy
            step_y = a10 * dx + a11 * dy
            tx += step_x
            ty += step_y
            if ok:
                r0 += sol[0, 2]
                r1 += sol[0, 3]
                if affine:  # A (I + D)
                    d00, d01, d10, d11 = sol[0, 4], sol[0, 5], sol[0, 6], sol[0, 7]
                    b00 = a00 * (1.0 + d00) + a01 * d10
                    b01 = a00 * d01 + a01 * (1.0 + d11)
                    b10 = a10 * (1.0 + d00) + a11 * d10
                    b11 = a10 * d01 + a11 * (1.0 + d11)
                    a00, a01, a10, a11 = b00, b01, b10, b11
            det = a00 * a11 - a01 * a10
            fro2 = a00 * a00 + a01 * a01 + a10 * a10 + a11 * a11
            disc = math.sqrt(max(fro2 * fro2 - 4.0 * det * det, 0.0))
            smax2, smin2 = 0.5 * (fro2 + disc), 0.5 * (fro2 - disc)
            regular = (ok and det > 0.0 and smax2 <= max_scale * max_scale
                       and smin2 >= 1.0 / (max_scale * max_scale)
                       and r1 >= 1.0 / max_gain and r1 <= max_gain)
            small = max(abs(step_x), abs(step_y)) < tol
            done = (not regular) or small or max(abs(tx - sx), abs(ty - sy)) > max_shift
            if done or it == max_iterations - 1:
                shift[j, 0], shift[j, 1] = tx, ty
                sigma[j, 0], sigma[j, 1], sigma_max[j] = sg_x, sg_y, sm
                A_out[j, 0, 0], A_out[j, 0, 1], A_out[j, 1, 0], A_out[j, 1, 1] = a00, a01, a10, a11
                gain[j], offset[j] = r1, r0
                s0_out[j] = math.sqrt(var0)
                converged[j] = regular and small
                iterations[j] = it + 1
                break


def _jit_all() -> Any:
    """Jit the kernel and helpers: FMA in the reads, reassociated dots, fixed at compile time."""
    jit_helpers(globals(), (_cubic, _compose, _merged, _read, _smoothed), CONTRACT)
    jit_helpers(globals(), (_read_blurred,))
    jit_helpers(globals(), (_dot,), REASSOC)
    return jit()(_lsm_matches)


#: the jitted kernel (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def _blur_arrays(blur: tuple[torch.Tensor, torch.Tensor] | None, n: int) -> tuple[np.ndarray, np.ndarray]:
    if blur is None:
        return np.zeros(n, np.bool_), np.zeros(n)
    return (np.ascontiguousarray(blur[0].cpu().numpy()),
            np.ascontiguousarray(blur[1].cpu().numpy().astype(np.float64)))


def _check_sizes(radius: int, max_iterations: int, *blurs) -> None:
    """Refuse sizes the kernel's buffers were not made for (radius, iterations, blur), so no caller
    can corrupt memory; ValueError naming the value."""
    if not 1 <= int(radius) <= MAX_WINDOW_RADIUS_PX:
        raise ValueError(f"LSM radius must be in [1, {MAX_WINDOW_RADIUS_PX}] pixels, got {radius}")
    if not 1 <= int(max_iterations) <= 50:
        raise ValueError(f"LSM max_iterations must be in [1, 50], got {max_iterations}")
    for blur in blurs:
        if blur is None:
            continue
        on, sigma = blur
        used = sigma[on]
        if used.numel() and not bool(torch.isfinite(used).all() and (used >= 0).all() and (used <= MAX_BLUR_PX).all()):
            raise ValueError(f"LSM blur must be finite and in [0, {MAX_BLUR_PX:g}] pixels, got up to "
                             f"{float(used.abs().max())}")


def lsm_frames(
    img_f: torch.Tensor | ImageStack,
    img_m: torch.Tensor | ImageStack,
    H_f_inv: torch.Tensor,
    frame_f: torch.Tensor,
    H_m_inv: torch.Tensor,
    frame_m: torch.Tensor,
    shift0: torch.Tensor,
    radius: int,
    *,
    blur_f: tuple[torch.Tensor, torch.Tensor] | None = None,
    blur_m: tuple[torch.Tensor, torch.Tensor] | None = None,
    affine: bool = True,
    max_iterations: int = 10,
    tol_px: float = DEFAULT_TOL_PX,
    max_shift_px: float | None = None,
) -> LSMResult:
    """LSM of n matches on the CPU: the fixed side's template read and aligned to the moving side,
    as ``lsm_align(frame_sampler(...), ...)`` would.

    ``H_f_inv``, ``H_m_inv`` ``(n, 3, 3)`` common frame -> image pixels; ``frame_f``, ``frame_m``
    ``(n, 2)`` centres; ``shift0`` ``(n, 2)`` start; ``blur_f``, ``blur_m`` as ``blur_px``; the rest
    as :func:`.align.lsm_align`. Returns :class:`~.result.LSMResult` on CPU tensors."""
    n = shift0.shape[0]
    _check_sizes(radius, max_iterations, blur_f, blur_m)
    ims_f, idx_f = image_arrays(img_f, n)
    ims_m, idx_m = image_arrays(img_m, n)
    f64 = np.float64
    H_f, H_m = (np.ascontiguousarray(h.cpu().numpy().astype(f64)) for h in (H_f_inv, H_m_inv))
    c_f, c_m, s0 = (np.ascontiguousarray(v.cpu().numpy().astype(f64)) for v in (frame_f, frame_m, shift0))
    on_f, sigma_f = _blur_arrays(blur_f, n)
    on_m, sigma_m = _blur_arrays(blur_m, n)
    shift = s0.copy()
    sigma = np.full((n, 2), np.inf)
    sigma_max = np.full(n, np.inf)
    A = np.tile(np.eye(2), (n, 1, 1))
    gain, offset = np.ones(n), np.zeros(n)
    s0_out = np.full(n, np.nan)
    converged = np.zeros(n, np.bool_)
    iterations = np.zeros(n, np.int64)
    kernel = KERNELS()
    key = idx_f * len(ims_m) + idx_m
    order = np.argsort(key, kind="stable")
    keys, first = np.unique(key[order], return_index=True)
    for k, lo, hi in zip(keys.tolist(), first.tolist(), [*first[1:].tolist(), n], strict=True):
        rows = order[lo:hi].astype(np.int64)  # one call per (fixed image, moving image)
        kernel(ims_f[k // len(ims_m)], ims_m[k % len(ims_m)], rows, H_f, c_f, H_m, c_m, on_f, sigma_f,
               on_m, sigma_m, s0, int(radius), bool(affine), int(max_iterations), float(tol_px),
               math.inf if max_shift_px is None else float(max_shift_px), KEYS_A,
               float(MAX_SCALE), float(MAX_GAIN), shift, sigma, sigma_max, A, gain, offset,
               s0_out, converged, iterations)
    t = torch.from_numpy
    return LSMResult(shift=t(shift), sigma=t(sigma), sigma_max=t(sigma_max), affine=t(A), gain=t(gain),
                     offset=t(offset), residual_std=t(s0_out), converged=t(converged),
                     iterations=t(iterations))



def warm() -> bool:
    """Load (or compile) the kernel now on a small problem; whether it loaded. Never raises."""

    def example() -> None:
        g = torch.arange(48, dtype=torch.float32)
        img = torch.sin(g[:, None] * 0.3) * torch.cos(g[None] * 0.2)
        eye = torch.eye(3, dtype=torch.float64)[None]
        c = torch.tensor([[24.0, 23.0]], dtype=torch.float64)
        blur = (torch.ones(1, dtype=torch.bool), torch.full((1,), 0.5, dtype=torch.float64))
        lsm_frames(img, img, eye, c, eye, c, torch.zeros(1, 2, dtype=torch.float64), 3, blur_f=blur,
                   max_iterations=2)

    return KERNELS.warm(example)
