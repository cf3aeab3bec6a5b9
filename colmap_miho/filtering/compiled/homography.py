"""Compiled (numba) per-homography helpers of the filter's kernels: sign, adjugate, unit
norm, point transfer, inlier test, Hartley-normalised minimal DLT singular-value test, each on
one hypothesis in registers (what :mod:`..homography` computes on batches).

These are no kernels of their own: :mod:`..scoring` and :mod:`..ransac` call them from theirs.
:data:`KERNELS` jits them once, in this module's namespace (where they find each other), and
the kernel modules take the jitted functions into theirs before they jit their kernels."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit


def sign_of(v: float) -> float:
    """-1, 0 or 1 (0 for nan: a nan sign fails every sign test, as numpy's nan sign does)."""
    if v > 0:
        return 1.0
    if v < 0:
        return -1.0
    return 0.0


def adjugate(e, out) -> None:
    """``out[9]`` = the adjugate of the row-major 3x3 ``e[9]`` (the products and differences
    of :func:`..homography.adjugate`)."""
    out[0] = e[4] * e[8] - e[5] * e[7]
    out[1] = e[2] * e[7] - e[1] * e[8]
    out[2] = e[1] * e[5] - e[2] * e[4]
    out[3] = e[5] * e[6] - e[3] * e[8]
    out[4] = e[0] * e[8] - e[2] * e[6]
    out[5] = e[2] * e[3] - e[0] * e[5]
    out[6] = e[3] * e[7] - e[4] * e[6]
    out[7] = e[1] * e[6] - e[0] * e[7]
    out[8] = e[0] * e[4] - e[1] * e[3]


def normalised(e) -> bool:
    """Scale the 9 entries ``e`` to unit Frobenius norm (in place; the norm at least 1e-300);
    whether all of them are finite then."""
    norm = 0.0
    for a in range(9):
        norm += e[a] * e[a]
    norm = max(np.sqrt(norm), 1e-300)
    finite = True
    for a in range(9):
        e[a] /= norm
        if not np.isfinite(e[a]):
            finite = False
    return finite


def transfer(h, X, Y, u, v):
    """``(e, w)``: squared transfer error of the point ``(X, Y)`` to ``(u, v)`` under the
    row-major ``h[9]``, and its ``w`` (:func:`..homography.transfer_error_sq`'s operations, in
    its order)."""
    w = h[6] * X
    w += h[7] * Y
    w += h[8]
    x = h[0] * X
    x += h[1] * Y
    x += h[2]
    x /= w
    x -= u
    x *= x
    y = h[3] * X
    y += h[4] * Y
    y += h[5]
    y /= w
    y -= v
    y *= y
    x += y
    return x, w


def hypothesis_rows(H, sign, Hinv, sign_inv, k, scaled, out):
    """``out[2 * halves, 9]``: hypothesis ``k``'s forward and backward matrices, half by
    half, times their sample's signs when ``scaled`` (an exact change: the signs are +-1)."""
    for h in range(H.shape[1]):
        for e in range(9):
            f, b = H[k, h, e // 3, e % 3], Hinv[k, h, e // 3, e % 3]
            if scaled:
                f *= sign[k, h]
                b *= sign_inv[k, h]
            out[2 * h, e] = f
            out[2 * h + 1, e] = b


def mask_row(hk, pts, t2, s2, out):
    """``out[n]``: whether each match is inside under the sign-scaled matrices ``hk``
    ``(2 * halves, 9)`` (:func:`hypothesis_rows`), every half and direction (:func:`.scoring.inlier_masks`)."""
    terms = hk.shape[0]
    for i in range(pts.shape[3]):
        inside = True
        for t in range(terms):
            h, d = t // 2, t % 2
            e, w = transfer(hk[t], pts[h, d, 0, i], pts[h, d, 1, i],
                             pts[h, 1 - d, 0, i], pts[h, 1 - d, 1, i])
            if s2 != 1.0:
                e *= s2
            if not (e <= t2 and w > 0):
                inside = False
                break
        out[i] = inside


def normalise4(pts, out):
    """Hartley-normalised copy ``out[4, 2]`` of the 4 points ``pts[4, 2]``
    (:func:`..homography.normalised`)."""
    cx = (pts[0, 0] + pts[1, 0] + pts[2, 0] + pts[3, 0]) / 4
    cy = (pts[0, 1] + pts[1, 1] + pts[2, 1] + pts[3, 1]) / 4
    dist = 0.0
    for i in range(4):
        out[i, 0] = pts[i, 0] - cx
        out[i, 1] = pts[i, 1] - cy
        dist += np.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2)
    scale = np.sqrt(2.0) / max(dist / 4, 1e-12)
    for i in range(4):
        out[i, 0] *= scale
        out[i, 1] *= scale


def sv_ok_one(sample, k, src_all, dst_all, min_sv, p, q, s, d, A) -> bool:
    """Whether sample ``k``'s normalised minimal DLT system has its smallest singular value
    above ``min_sv`` in every half (:func:`.scoring.singular_value_ok`); ``p``, ``q``, ``s``, ``d``
    ``(4, 2)`` and ``A`` ``(8, 9)`` (zero where no entry is written) scratch."""
    for h in range(src_all.shape[1]):
        for i in range(4):
            for c in range(2):
                p[i, c] = src_all[sample[k, i], h, c]
                q[i, c] = dst_all[sample[k, i], h, c]
        normalise4(p, s)
        normalise4(q, d)
        for i in range(4):
            x, y, u, v = s[i, 0], s[i, 1], d[i, 0], d[i, 1]
            A[2 * i, 0] = x
            A[2 * i, 1] = y
            A[2 * i, 2] = 1.0
            A[2 * i, 6] = -u * x
            A[2 * i, 7] = -u * y
            A[2 * i, 8] = -u
            A[2 * i + 1, 3] = x
            A[2 * i + 1, 4] = y
            A[2 * i + 1, 5] = 1.0
            A[2 * i + 1, 6] = -v * x
            A[2 * i + 1, 7] = -v * y
            A[2 * i + 1, 8] = -v
        ev = np.linalg.eigvalsh(A @ A.T)
        if not np.sqrt(max(ev[0], 0.0)) > min_sv:
            return False
    return True


def _jit_all() -> dict[str, Any]:
    """Jit the helpers in this module (so that those calling each other find each other
    jitted) and return them by name, for the kernel modules that call them."""
    j = jit()
    jitted = {f.__name__: j(f) for f in (sign_of, adjugate, normalised, transfer, hypothesis_rows, mask_row,
                                         normalise4, sv_ok_one)}
    globals().update(jitted)
    return jitted


#: the jitted helpers by name (on the first call of a kernel that uses them).
KERNELS = Kernels(_jit_all)
