"""Compiled (numba) NCC search and iterated sub-pixel step on CPU tensors: :func:`evaluate` and
:func:`subpixel` do what :func:`.search.evaluate_direction` (plain search) and
:func:`.subpixel.iterate_subpixel` do, one loop per match; results differ at float rounding only."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ...compiled import CONTRACT, REASSOC, Kernels, jit, jit_helpers
from ..warping import ImageStack, image_arrays

#: the constants of the torch path (:mod:`..warping`, :mod:`.correlation`, :mod:`.subpixel`).
_SINGULAR_DET = 1e-12
_MIN_W = 1e-8
_EPS_NORM = 1e-6
_MIN_CURVATURE = 1e-4
_CONVERGED_PX = 1e-3
_SEPARATED_PX = 2


# ----------------------------------------------------------------------------------------------
# geometry: the float64 operations of the torch path in its order (compiled without fastmath)


def _invert(H, out) -> bool:
    """``out`` = H^-1 by the adjugate; False (and the identity) when singular or not finite."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 0], H[1, 1], H[1, 2]
    g, h, i = H[2, 0], H[2, 1], H[2, 2]
    a00, a01, a02 = e * i - f * h, c * h - b * i, b * f - c * e
    a10, a11, a12 = f * g - d * i, a * i - c * g, c * d - a * f
    a20, a21, a22 = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * a00 + b * a10 + c * a20
    big = 0.0
    for r in range(3):
        for k in range(3):
            big = max(big, abs(H[r, k]))
    scale = max(big, 1e-300) ** 3
    ok = np.isfinite(det) and abs(det) > _SINGULAR_DET * scale
    if not ok:
        for r in range(3):
            for k in range(3):
                out[r, k] = 1.0 if r == k else 0.0
        return False
    out[0, 0], out[0, 1], out[0, 2] = a00 / det, a01 / det, a02 / det
    out[1, 0], out[1, 1], out[1, 2] = a10 / det, a11 / det, a12 / det
    out[2, 0], out[2, 1], out[2, 2] = a20 / det, a21 / det, a22 / det
    return True


def _to_frame(H, x: float, y: float) -> tuple[float, float]:
    X = H[0, 0] * x + H[0, 1] * y + H[0, 2]
    Y = H[1, 0] * x + H[1, 1] * y + H[1, 2]
    W = max(H[2, 0] * x + H[2, 1] * y + H[2, 2], 1e-12)
    return X / W, Y / W


def _inside(Hi, cx: float, cy: float, radius: int, h: int, w: int) -> bool:
    """The corners of the square up to ``radius`` around (cx, cy) map in front and inside the image."""
    for corner in range(4):
        px = cx + (radius if corner % 2 == 1 else -radius)
        py = cy + (radius if corner >= 2 else -radius)
        X = Hi[0, 0] * px + Hi[0, 1] * py + Hi[0, 2]
        Y = Hi[1, 0] * px + Hi[1, 1] * py + Hi[1, 2]
        W = Hi[2, 0] * px + Hi[2, 1] * py + Hi[2, 2]
        if not W > _MIN_W:
            return False
        x, y = X / W, Y / W
        if not (x >= 0.0 and x <= w - 1.0 and y >= 0.0 and y <= h - 1.0):
            return False
    return True


def _centre_good(Hi, cx: float, cy: float) -> bool:
    return Hi[2, 0] * cx + Hi[2, 1] * cy + Hi[2, 2] > _MIN_W


# ----------------------------------------------------------------------------------------------
# samples and NCC (compiled with contracted multiply-adds)


def _sample(img, Hi, cx: float, cy: float, radius: int, out, pos) -> None:
    """``out`` ``(S, S)`` float32 ``[y, x]``: ``img`` read bilinearly (zeros outside) at ``Hi (c +
    o)`` for integer offsets up to ``radius``; ``pos`` is work space."""
    h, w = img.shape
    X = Hi[0, 0] * cx + Hi[0, 1] * cy + Hi[0, 2]
    Y = Hi[1, 0] * cx + Hi[1, 1] * cy + Hi[1, 2]
    Wc = Hi[2, 0] * cx + Hi[2, 1] * cy + Hi[2, 2]
    wc = Wc if Wc > _MIN_W else 1.0
    xc, yc = X / wc, Y / wc
    b0, b1 = Hi[2, 0] / wc, Hi[2, 1] / wc
    m00, m01 = Hi[0, 0] / wc - xc * b0, Hi[0, 1] / wc - xc * b1
    m10, m11 = Hi[1, 0] / wc - yc * b0, Hi[1, 1] / wc - yc * b1
    affine = b0 == 0.0 and b1 == 0.0
    fw, fh = float(w), float(h)
    side = 2 * radius + 1
    pxs, pys = pos[0], pos[1]
    for iy in range(side):
        oy = float(iy - radius)
        ax, ay, aw = m01 * oy, m11 * oy, b1 * oy + 1.0
        if affine:
            for ix in range(side):
                ox = float(ix - radius)
                pxs[ix] = xc + (m00 * ox + ax)
                pys[ix] = yc + (m10 * ox + ay)
        else:
            for ix in range(side):
                ox = float(ix - radius)
                qw = max(b0 * ox + aw, 1e-6)
                pxs[ix] = xc + (m00 * ox + ax) / qw
                pys[ix] = yc + (m10 * ox + ay) / qw
        orow = out[iy]
        for ix in range(side):
            px, py = pxs[ix], pys[ix]
            v = 0.0
            if px > -1.0 and px < fw and py > -1.0 and py < fh:
                fx, fy = np.floor(px), np.floor(py)
                x0, y0 = int(fx), int(fy)
                tx, ty = px - fx, py - fy
                if x0 >= 0 and x0 + 1 < w and y0 >= 0 and y0 + 1 < h:
                    r0, r1 = img[y0], img[y0 + 1]
                    v = ((r0[x0] * (1.0 - tx) + r0[x0 + 1] * tx) * (1.0 - ty)
                         + (r1[x0] * (1.0 - tx) + r1[x0 + 1] * tx) * ty)
                else:
                    for k in range(4):
                        xx, yy = x0 + k % 2, y0 + k // 2
                        if xx >= 0 and xx < w and yy >= 0 and yy < h:
                            wx = tx if k % 2 == 1 else 1.0 - tx
                            wy = ty if k >= 2 else 1.0 - ty
                            v += img[yy, xx] * (wx * wy)
            orow[ix] = v


def _normalize(tpl, out) -> float:
    """``out``: the zero-mean unit-norm template (zero when flat); returns its sum of squared deviations."""
    n = tpl.shape[0]
    mean = 0.0
    for y in range(n):
        rs = 0.0
        for x in range(n):
            rs += tpl[y, x]
        mean += rs
    mean /= n * n
    ss = 0.0
    for y in range(n):
        rs = 0.0
        for x in range(n):
            d = tpl[y, x] - mean
            out[y, x] = d
            rs += d * d
        ss += rs
    norm = math.sqrt(ss)
    inv = 1.0 / norm if norm > _EPS_NORM else 0.0
    for y in range(n):
        for x in range(n):
            out[y, x] *= inv
    return ss


def _ncc(win, tn, So: int, out, wc, box, cols) -> None:
    """``out`` ``[y, x]``: NCC of the normalised template ``tn`` with each patch of ``win`` (Sw = St
    + So - 1); ``wc``, ``box`` and ``cols`` are work space."""
    St = tn.shape[0]
    Sw = St + So - 1
    mean = 0.0
    for y in range(Sw):
        rs = 0.0
        for x in range(Sw):
            rs += win[y, x]
        mean += rs
    mean /= Sw * Sw
    s1, s2 = box[0], box[1]
    for x in range(Sw + 1):
        s1[0, x] = 0.0
        s2[0, x] = 0.0
    for y in range(Sw):
        a1 = 0.0
        a2 = 0.0
        s1[y + 1, 0] = 0.0
        s2[y + 1, 0] = 0.0
        for x in range(Sw):
            d = win[y, x] - mean
            wc[y, x] = d
            a1 += d
            a2 += d * d
            s1[y + 1, x + 1] = s1[y, x + 1] + a1
            s2[y + 1, x + 1] = s2[y, x + 1] + a2
    _corr(wc, tn, So, out, cols)
    n = float(St * St)
    for y in range(So):
        for x in range(So):
            b1 = s1[y + St, x + St] - s1[y, x + St] - s1[y + St, x] + s1[y, x]
            b2 = s2[y + St, x + St] - s2[y, x + St] - s2[y + St, x] + s2[y, x]
            wn = math.sqrt(max(b2 - b1 * b1 / n, 0.0))
            v = out[y, x] / wn if wn > _EPS_NORM else 0.0
            out[y, x] = min(max(v, -1.0), 1.0)


def _corr(wc, tn, So: int, out, cols) -> None:
    """``out[y, x]``: cross-correlation of ``tn`` with ``wc``'s patch at (x, y), one contiguous dot
    per offset (``cols``: column bands, work space). Reassociated, but the same order for every
    match."""
    St = tn.shape[0]
    Sw = St + So - 1
    band = Sw * St
    n = St * St
    tf = tn.ravel()
    for x in range(So):
        b = cols[x * band:(x + 1) * band]
        for r in range(Sw):
            row = wc[r]
            for k in range(St):
                b[r * St + k] = row[x + k]
    for y in range(So):
        for x in range(So):
            p = cols[x * band + y * St:x * band + y * St + n]
            acc = 0.0
            for i in range(n):
                acc += tf[i] * p[i]
            out[y, x] = acc


def _parabola(c0: float, cm: float, cp: float, valid: bool) -> float:
    """Vertex of the parabola through (-1, cm), (0, c0), (1, cp) clamped to [-0.5, 0.5]; 0 if invalid."""
    den = cm - 2.0 * c0 + cp
    if not (valid and den < -_MIN_CURVATURE):
        return 0.0
    return min(max(0.5 * (cm - cp) / den, -0.5), 0.5)


# ----------------------------------------------------------------------------------------------
# the sub-pixel step


def _subpixel_matches(img, rows, H, c, off, tpl, radius: int, iterations: int, out) -> None:
    """The iterated sub-pixel step of the matches ``rows``: ``out[j]`` ``(2,)`` float64 from ``off[j]``."""
    St = 2 * radius + 1
    side = St + 2
    tn = np.empty((St, St))
    win = np.empty((side, side), np.float32)
    m3 = np.empty((3, 3))
    wc = np.empty((side, side))
    box = np.empty((2, side + 1, side + 1))
    cols = np.empty(3 * side * St)
    pos = np.empty((2, side))
    for q in range(rows.shape[0]):
        j = rows[q]
        _normalize(tpl[j], tn)
        ox, oy = off[j, 0], off[j, 1]
        for _ in range(iterations):
            _sample(img, H[j], c[j, 0] + ox, c[j, 1] + oy, radius + 1, win, pos)
            _ncc(win, tn, 3, m3, wc, box, cols)
            c0 = m3[1, 1]
            sx = _parabola(c0, m3[1, 0], m3[1, 2], True)
            sy = _parabola(c0, m3[0, 1], m3[2, 1], True)
            ox += sx
            oy += sy
            if max(abs(sx), abs(sy)) < _CONVERGED_PX:
                break
        out[j, 0], out[j, 1] = ox, oy


# ----------------------------------------------------------------------------------------------
# the search


def _ellipse(tpl, radius: int, use_mask: bool, mask) -> tuple[float, float]:
    """The structure tensor's ``(lam_min, lam_max)`` of ``tpl``; writes the NCC* mask when ``use_mask``."""
    n = tpl.shape[0]
    a = 0.0
    b = 0.0
    c = 0.0
    for y in range(1, n - 1):
        for x in range(1, n - 1):
            gx = 0.5 * (float(tpl[y, x + 1]) - float(tpl[y, x - 1]))
            gy = 0.5 * (float(tpl[y + 1, x]) - float(tpl[y - 1, x]))
            a += gx * gx
            b += gx * gy
            c += gy * gy
    half_tr = 0.5 * (a + c)
    disc = math.sqrt(0.25 * (a - c) ** 2 + b * b)
    lam_max = half_tr + disc
    lam_min = max(half_tr - disc, 0.0)
    if not use_mask:
        return lam_min, lam_max
    v1x, v1y = b, lam_max - a
    v2x, v2y = lam_max - c, b
    n1, n2 = math.sqrt(v1x * v1x + v1y * v1y), math.sqrt(v2x * v2x + v2y * v2y)
    vx, vy = (v1x, v1y) if n1 >= n2 else (v2x, v2y)
    nv = math.sqrt(vx * vx + vy * vy)
    dx, dy = (vx / nv, vy / nv) if nv > 1e-12 else (1.0, 0.0)
    ratio = lam_min / max(lam_max, 1e-20) if lam_max > 0 else 1.0
    minor = max(radius * math.sqrt(ratio), 0.5)
    side = 2 * radius + 1
    for iy in range(side):
        yy = float(iy - radius)
        for ix in range(side):
            xx = float(ix - radius)
            g = (xx * dx + yy * dy) / radius
            e = (-xx * dy + yy * dx) / minor
            mask[iy, ix] = g * g + e * e <= 1.0 + 1e-6
    return lam_min, lam_max


def _peaks(maps, n_k: int, So: int, use_mask: bool, mask, cut: int, kk: int
           ) -> tuple[int, int, int, float, float, float, float, bool]:
    """:func:`.correlation.find_peaks` of ``maps``: (k, iy, ix, peak, NCC, sub-pixel x, y, border)."""
    best = -math.inf
    bk, by, bx = 0, 0, 0
    first = True
    for k in range(n_k):
        if kk >= 0 and k != kk:
            continue
        for y in range(So):
            for x in range(So):
                v = maps[k, y, x]
                if use_mask and not mask[y + cut, x + cut]:
                    v = -2.0
                if first or v > best:
                    best, bk, by, bx = v, k, y, x
                    first = False
    m = maps[bk]
    c0 = m[by, bx]
    vx = bx > 0 and bx < So - 1
    vy = by > 0 and by < So - 1
    sx = _parabola(c0, m[by, max(bx - 1, 0)], m[by, min(bx + 1, So - 1)], vx)
    sy = _parabola(c0, m[max(by - 1, 0), bx], m[min(by + 1, So - 1), bx], vy)
    border = not (vx and vy)
    if use_mask and not border:
        local = c0
        for y in range(max(by - 1, 0), min(by + 2, So)):
            for x in range(max(bx - 1, 0), min(bx + 2, So)):
                local = max(local, m[y, x])
        border = local > c0 + 1e-6
    return bk, by, bx, best, c0, sx, sy, border


def _second(maps, k: int, So: int, use_mask: bool, mask, cut: int, py: int, px: int) -> float:
    """The best peak of ``maps[k]`` at least ``_SEPARATED_PX`` offsets from (py, px); at least -1."""
    out = -1.0
    for y in range(So):
        for x in range(So):
            if abs(y - py) < _SEPARATED_PX and abs(x - px) < _SEPARATED_PX:
                continue
            v = maps[k, y, x]
            if use_mask and not mask[y + cut, x + cut]:
                v = -2.0
            if v <= out:
                continue
            local = True
            for yy in range(max(y - 1, 0), min(y + 2, So)):
                for xx in range(max(x - 1, 0), min(x + 2, So)):
                    w = maps[k, yy, xx]
                    if use_mask and not mask[yy + cut, xx + cut]:
                        w = -2.0
                    if w > v:
                        local = False
            if local:
                out = v
    return out


def _search_matches(img_f, img_m, rows, xf, xm, H, f: int, m: int, r: int, s0: int, s: int,
                    use_mask: bool, min_std: float,
                    peak, centre, border, zero, inside, valid, flat, offset,
                    H_inv, frame_m, H_f_inv, frame_f, template, researched, second) -> None:
    """The search of the matches ``rows``; outputs written into the ``(J, ...)`` arrays."""
    n_pass = H.shape[1]
    St = 2 * r + 1
    Sw = 2 * (r + s) + 1
    So = 2 * s + 1
    hf, wf = img_f.shape
    hm, wm = img_m.shape
    tpl = np.empty((n_pass, St, St), np.float32)
    tn = np.empty((n_pass, St, St))
    win = np.empty((Sw, Sw), np.float32)
    wc = np.empty((Sw, Sw))
    box = np.empty((2, Sw + 1, Sw + 1))
    cols = np.empty(So * Sw * St)
    pos = np.empty((2, Sw))
    maps = np.empty((n_pass, So, So))
    mask = np.ones((So, So), np.bool_)
    Hfi = np.empty((n_pass, 3, 3))
    Hmi = np.empty((n_pass, 3, 3))
    cf = np.empty((n_pass, 2))
    cm = np.empty((n_pass, 2))
    for q in range(rows.shape[0]):
        j = rows[q]
        ok = True
        ins = True
        ss = 0.0  # pass 0's template: its squared deviations (the flatness test)
        for p in range(n_pass):
            ok_f = _invert(H[j, p, f], Hfi[p])
            ok_m = _invert(H[j, p, m], Hmi[p])
            ok = ok and ok_f and ok_m
            cf[p, 0], cf[p, 1] = _to_frame(H[j, p, f], xf[j, 0], xf[j, 1])
            cm[p, 0], cm[p, 1] = _to_frame(H[j, p, m], xm[j, 0], xm[j, 1])
            _sample(img_f, Hfi[p], cf[p, 0], cf[p, 1], r, tpl[p], pos)
            ss_p = _normalize(tpl[p], tn[p])
            if p == 0:
                ss = ss_p
            ins = (ins and _centre_good(Hfi[p], cf[p, 0], cf[p, 1])
                   and _inside(Hfi[p], cf[p, 0], cf[p, 1], r, hf, wf)
                   and _centre_good(Hmi[p], cm[p, 0], cm[p, 1])
                   and _inside(Hmi[p], cm[p, 0], cm[p, 1], r + s, hm, wm))
        t0 = tpl[0]
        is_flat = math.sqrt(ss / (St * St - 1)) < min_std
        _ellipse(t0, s, use_mask, mask)
        radius = s0
        again = False
        while True:
            so = 2 * radius + 1
            for p in range(n_pass):
                _sample(img_m, Hmi[p], cm[p, 0], cm[p, 1], r + radius, win, pos)
                _ncc(win, tn[p], so, maps[p], wc, box, cols)
            cut = s - radius
            bk, by, bx, best, c0, sx, sy, on_border = _peaks(maps, n_pass, so, use_mask, mask, cut, -1)
            if radius == s:
                break
            near = False
            for p in range(n_pass):
                near = near or _peaks(maps, n_pass, so, use_mask, mask, cut, p)[7]
            if not (near and ok and ins and not is_flat):
                break
            radius = s
            again = True
        cen = -math.inf
        for p in range(n_pass):
            cen = max(cen, maps[p, radius, radius])
        peak[j] = best
        second[j] = _second(maps, bk, so, use_mask, mask, s - radius, by, bx)
        centre[j] = cen
        border[j] = on_border
        zero[j] = by == radius and bx == radius
        inside[j] = ins
        valid[j] = ok
        flat[j] = is_flat
        offset[j, 0] = (bx - radius) + sx
        offset[j, 1] = (by - radius) + sy
        frame_m[j, 0], frame_m[j, 1] = cm[bk, 0], cm[bk, 1]
        frame_f[j, 0], frame_f[j, 1] = cf[bk, 0], cf[bk, 1]
        for a in range(3):
            for b in range(3):
                H_inv[j, a, b] = Hmi[bk, a, b]
                H_f_inv[j, a, b] = Hfi[bk, a, b]
        for y in range(St):
            for x in range(St):
                template[j, y, x] = tpl[bk, y, x]
        researched[j] = again


# ----------------------------------------------------------------------------------------------
# compiling and calling


def _jit_all() -> dict[str, Any]:
    """Jit the kernels: geometry exact, reads and maps with FMA, correlation dots also reassociated."""
    jit_helpers(globals(), (_corr,), REASSOC)
    jit_helpers(globals(), (_invert, _to_frame, _inside, _centre_good))
    jit_helpers(globals(), (_sample, _normalize, _ncc, _parabola, _ellipse, _peaks, _second), CONTRACT)
    fused = jit(CONTRACT)
    return {"subpixel": fused(_subpixel_matches), "search": fused(_search_matches)}


#: the jitted kernels (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def _groups(key: np.ndarray) -> list[tuple[int, np.ndarray]]:
    if key.size and (key == key[0]).all():
        return [(int(key[0]), np.arange(key.size, dtype=np.int64))]
    order = np.argsort(key, kind="stable")
    keys, first = np.unique(key[order], return_index=True)
    bounds = [*first.tolist(), key.size]
    return [(int(k), order[lo:hi].astype(np.int64)) for k, lo, hi in zip(keys.tolist(), bounds[:-1], bounds[1:],
                                                                        strict=True)]


def _f64(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(np.float64, copy=False))


def subpixel(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    offset: torch.Tensor,
    templates: torch.Tensor,
    template_radius: int,
    iterations: int,
) -> torch.Tensor:
    """:func:`.subpixel.iterate_subpixel` on CPU tensors: ``(n, 2)`` float64 refined offsets."""
    n = offset.shape[0]
    if iterations <= 0 or n == 0:
        return offset
    ims, idx = image_arrays(image, n)
    H, c, off = _f64(H_inv), _f64(centres), _f64(offset)
    tpl = np.ascontiguousarray(templates.detach().cpu().numpy().astype(np.float32, copy=False))
    out = off.copy()
    kernel = KERNELS()["subpixel"]
    for k, rows in _groups(idx):
        kernel(ims[k], rows, H, c, off, tpl, int(template_radius), int(iterations), out)
    return torch.from_numpy(out)


def serves(passes: list, template_radius: int) -> bool:
    """Whether :func:`evaluate` serves these passes: one unperturbed square template each."""
    offs = passes[0][1]
    St = 2 * template_radius + 1
    if offs.ndim != 3 or offs.shape[0] != 1 or offs.shape[1] != St * St:
        return False
    if not all(o is offs or torch.equal(o, offs) for _, o, _ in passes):
        return False
    r = torch.arange(-template_radius, template_radius + 1, dtype=offs.dtype, device=offs.device)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    return bool(torch.equal(offs[0], torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)))


def evaluate(
    img_f: torch.Tensor | ImageStack,
    img_m: torch.Tensor | ImageStack,
    x_f: torch.Tensor,
    x_m: torch.Tensor,
    passes: list,
    f: int,
    m: int,
    *,
    template_radius: int,
    search_radius: int,
    inner_radius: int,
    ellipse_mask: bool,
    min_template_std: float,
) -> dict[str, torch.Tensor]:
    """:func:`.search.evaluate_direction` on CPU tensors, plus ``researched`` ``(J,)``: the matches
    searched again over the full radius."""
    J = x_f.shape[0]
    ims_f, idx_f = image_arrays(img_f, J)
    ims_m, idx_m = image_arrays(img_m, J)
    H = np.ascontiguousarray(np.stack([_f64(h) for h, _, _ in passes], axis=1))  # (J, n_pass, 2, 3, 3)
    xf, xm = _f64(x_f), _f64(x_m)
    r, s = int(template_radius), int(search_radius)
    s0 = int(inner_radius) if 0 < inner_radius < s else s
    St = 2 * r + 1
    out = {
        "peak": np.zeros(J), "centre": np.zeros(J), "border": np.zeros(J, np.bool_),
        "zero": np.zeros(J, np.bool_), "inside": np.zeros(J, np.bool_), "valid": np.zeros(J, np.bool_),
        "flat": np.zeros(J, np.bool_), "offset": np.zeros((J, 2)),
        "H_inv": np.zeros((J, 3, 3)), "frame_m": np.zeros((J, 2)), "H_f_inv": np.zeros((J, 3, 3)),
        "frame_f": np.zeros((J, 2)), "template": np.zeros((J, St, St), np.float32),
        "researched": np.zeros(J, np.bool_), "second": np.zeros(J),
    }
    kernel = KERNELS()["search"]
    n_m = len(ims_m)
    for key, rows in _groups(idx_f * n_m + idx_m):
        kernel(ims_f[key // n_m], ims_m[key % n_m], rows, xf, xm, H, int(f), int(m), r, s0, s,
               bool(ellipse_mask), float(min_template_std), *out.values())
    return {k: torch.from_numpy(v) for k, v in out.items()}


def warm() -> bool:
    """Load (or compile) the kernels now on a small problem; whether they loaded. Never raises."""

    def example() -> None:
        g = torch.arange(64, dtype=torch.float32)
        img = torch.sin(g[:, None] * 0.3) * torch.cos(g[None] * 0.2)
        eye = torch.eye(3, dtype=torch.float64)
        x = torch.tensor([[30.0, 31.0]], dtype=torch.float64)
        grid = torch.stack(torch.meshgrid(torch.arange(-2.0, 3.0, dtype=torch.float64),
                                          torch.arange(-2.0, 3.0, dtype=torch.float64), indexing="xy"), -1)
        passes = [(eye.expand(1, 2, 3, 3), grid.reshape(1, -1, 2), None)]
        r = evaluate(img, img, x, x, passes, 0, 1, template_radius=2, search_radius=3, inner_radius=1,
                     ellipse_mask=False, min_template_std=0.0)
        subpixel(img, r["H_inv"], r["frame_m"], r["offset"], r["template"], 2, 2)

    return KERNELS.warm(example)
