"""Compiled (numba) kernels of :mod:`..scoring`: each replaces a chain of small numpy calls
of a RANSAC batch with one call.

- :func:`hypotheses`: reflection check, closed-form 4-point solver with the sample's
  quasi-affine signs, adjugates and the one-way float32 inlier bound on the pool, fused
  (:func:`..scoring.hypotheses_from_samples` then :func:`..scoring.one_way_count`);
- :func:`singular_value_ok`, :func:`inlier_masks`, :func:`error_sq`: full scoring.

The masks and the errors are the same decisions / bits as numpy's for the same inputs; the
solver and the singular values add their products in a fixed order where numpy's matmul
(BLAS) may fuse or reorder them, so homographies can differ in the last bits, and with them,
rarely, a borderline decision."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit, jit_helpers
from . import homography
from .homography import adjugate, hypothesis_rows, mask_row, normalised, sign_of, sv_ok_one, transfer


def _basis_map(px, py, A, lam, work):
    """Fill ``A[9]`` (row-major ``P diag(lam)``) and ``lam[3]`` for the 4 points ``px[4]``,
    ``py[4]`` (:func:`..homography._basis_map`); returns ``det(P)``. ``work[18]`` scratch."""
    P = work[:9]
    adj = work[9:18]
    for c in range(3):
        P[c] = px[c]
        P[3 + c] = py[c]
        P[6 + c] = 1.0
    adjugate(P, adj)
    for r in range(3):
        lam[r] = adj[3 * r] * px[3] + adj[3 * r + 1] * py[3] + adj[3 * r + 2]
    det = P[0] * adj[0]
    det += P[1] * adj[3]
    det += P[2] * adj[6]
    for r in range(3):
        for c in range(3):
            A[3 * r + c] = P[3 * r + c] * lam[c]
    return det


def _one_sign(s) -> bool:
    """The 4 signs ``s[4]`` are one nonzero sign."""
    return s[0] * s[1] > 0 and s[0] * s[2] > 0 and s[0] * s[3] > 0


_TRIANGLES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


def _orientation(pts, i, j, k) -> float:
    """Signed doubled area of the triangle of points ``i, j, k`` of ``pts`` ``(N, 2)``
    (:func:`..homography.triangle_orientations`)."""
    ax = pts[j, 0] - pts[i, 0]
    ay = pts[j, 1] - pts[i, 1]
    bx = pts[k, 0] - pts[i, 0]
    by = pts[k, 1] - pts[i, 1]
    return ax * by - ay * bx


def _hypotheses(sample, ok, x1, x2, src_all, dst_all, reflection, X, Y, x2p, y2p, t2):
    """See :func:`hypotheses`: ``(K, H, Hinv, sign, sign_inv, sample_out, ub)``, the first
    ``K`` rows of each output valid."""
    B = sample.shape[0]
    nh = src_all.shape[1]
    n = X.shape[0]
    H = np.empty((B, nh, 3, 3))
    Hinv = np.empty((B, nh, 3, 3))
    sign = np.empty((B, nh))
    sign_inv = np.empty((B, nh))
    out_sample = np.empty((B, 4), dtype=np.int64)
    ub = np.zeros(B, dtype=np.int64)
    px = np.empty(4)
    py = np.empty(4)
    qx = np.empty(4)
    qy = np.empty(4)
    A = np.empty(9)
    Bm = np.empty(9)
    adjA = np.empty(9)
    Hm = np.empty(9)
    Hi = np.empty(9)
    lam = np.empty(3)
    mu = np.empty(3)
    work = np.empty(18)
    s_fwd = np.empty(4)
    s_inv = np.empty(4)
    h32 = np.empty(9, dtype=np.float32)
    K = 0
    for b in range(B):
        if not ok[b]:
            continue
        if reflection:
            good = True
            for t in range(4):
                i, j, k = _TRIANGLES[t]
                o1 = _orientation(x1, sample[b, i], sample[b, j], sample[b, k])
                o2 = _orientation(x2, sample[b, i], sample[b, j], sample[b, k])
                if not o1 * o2 > 0:
                    good = False
                    break
            if not good:
                continue
        valid = True
        for h in range(nh):
            for i in range(4):
                m = sample[b, i]
                px[i] = src_all[m, h, 0]
                py[i] = src_all[m, h, 1]
                qx[i] = dst_all[m, h, 0]
                qy[i] = dst_all[m, h, 1]
            det_p = _basis_map(px, py, A, lam, work)
            det_q = _basis_map(qx, qy, Bm, mu, work)
            adjugate(A, adjA)
            for r in range(3):
                for c in range(3):
                    Hm[3 * r + c] = (Bm[3 * r] * adjA[c] + Bm[3 * r + 1] * adjA[3 + c]
                                     + Bm[3 * r + 2] * adjA[6 + c])
            if not normalised(Hm):
                valid = False
            sl0, sl1, sl2 = sign_of(lam[0]), sign_of(lam[1]), sign_of(lam[2])
            sm0, sm1, sm2 = sign_of(mu[0]), sign_of(mu[1]), sign_of(mu[2])
            sdp, sdq = sign_of(det_p), sign_of(det_q)
            s_det_a = sdp * sl0 * sl1 * sl2
            s_det_b = sdq * sm0 * sm1 * sm2
            s_fwd[0] = s_det_a * sm0 * sl0
            s_fwd[1] = s_det_a * sm1 * sl1
            s_fwd[2] = s_det_a * sm2 * sl2
            s_fwd[3] = s_det_a * sdq * sdp
            s_ab = s_det_a * s_det_b
            s_inv[0] = s_ab * sl0 * sm0
            s_inv[1] = s_ab * sl1 * sm1
            s_inv[2] = s_ab * sl2 * sm2
            s_inv[3] = s_ab * sdp * sdq
            if not (_one_sign(s_fwd) and _one_sign(s_inv)):
                valid = False
            if not valid:
                break
            adjugate(Hm, Hi)
            for r in range(3):
                for c in range(3):
                    H[K, h, r, c] = Hm[3 * r + c]
                    Hinv[K, h, r, c] = Hi[3 * r + c]
            sign[K, h] = s_fwd[0]
            sign_inv[K, h] = s_inv[0]
        if not valid:
            continue
        for i in range(4):
            out_sample[K, i] = sample[b, i]
        # One-way bound: first half, forward, float32, division-free, sign-normalised.
        for e in range(9):
            h32[e] = np.float32(H[K, 0, e // 3, e % 3] * sign[K, 0])
        count = 0
        for i in range(n):
            xi = X[i]
            yi = Y[i]
            W = h32[6] * xi
            W += h32[7] * yi
            W += h32[8]
            U = h32[0] * xi
            U += h32[1] * yi
            U += h32[2]
            U -= W * x2p[i]
            V = h32[3] * xi
            V += h32[4] * yi
            V += h32[5]
            V -= W * y2p[i]
            U *= U
            V *= V
            U += V
            W2 = W * W
            W2 *= t2
            if W > 0 and U <= W2:
                count += 1
        ub[K] = count
        K += 1
    return K, H, Hinv, sign, sign_inv, out_sample, ub


def _inlier_masks(H, Hinv, sign, sign_inv, pts, t2, s2):
    """See :func:`inlier_masks`."""
    K = H.shape[0]
    terms = 2 * H.shape[1]
    n = pts.shape[3]
    out = np.zeros((K, n), dtype=np.bool_)
    hk = np.empty((terms, 9))
    for k in range(K):
        hypothesis_rows(H, sign, Hinv, sign_inv, k, True, hk)
        mask_row(hk, pts, t2, s2, out[k])
    return out


def _error_sq(H, Hinv, sign, sign_inv, pts, s2):
    """See :func:`error_sq`."""
    K = H.shape[0]
    terms = 2 * H.shape[1]
    n = pts.shape[3]
    out = np.empty((K, n))
    hk = np.empty((terms, 9))
    for k in range(K):
        hypothesis_rows(H, sign, Hinv, sign_inv, k, False, hk)
        for i in range(n):
            err = 0.0
            for t in range(terms):
                h, d = t // 2, t % 2
                e, w = transfer(hk[t], pts[h, d, 0, i], pts[h, d, 1, i],
                                 pts[h, 1 - d, 0, i], pts[h, 1 - d, 1, i])
                w *= sign[k, h] if d == 0 else sign_inv[k, h]
                if not w > 0:
                    e = np.inf
                if not e <= err:  # the max; nan only where w == 0, made inf above
                    err = e
            if s2 != 1.0:
                err *= s2
            out[k, i] = err
    return out


def _singular_value_ok(sample, src_all, dst_all, min_sv):
    """See :func:`singular_value_ok`."""
    K = sample.shape[0]
    ok = np.ones(K, dtype=np.bool_)
    p = np.empty((4, 2))
    q = np.empty((4, 2))
    s = np.empty((4, 2))
    d = np.empty((4, 2))
    A = np.zeros((8, 9))
    for k in range(K):
        ok[k] = sv_ok_one(sample, k, src_all, dst_all, min_sv, p, q, s, d, A)
    return ok


def _jit_all() -> dict[str, Any]:
    """Jit every kernel and the helpers they call (numpy's error model: a division by zero
    gives inf / nan, and those entries fail the sign test)."""
    globals().update(homography.KERNELS())  # the shared helpers, jitted once
    jit_helpers(globals(), (_basis_map, _one_sign, _orientation))
    j = jit()
    return {f.__name__: j(f) for f in (_hypotheses, _inlier_masks, _error_sq, _singular_value_ok)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def hypotheses(sample: np.ndarray, ok: np.ndarray, x1: np.ndarray, x2: np.ndarray,
               src_all: np.ndarray, dst_all: np.ndarray, reflection: bool,
               pool_src: np.ndarray, pool_dst: np.ndarray, t2: float):
    """Hypotheses of the minimal samples ``(B, 4)`` (global indices) that pass ``ok`` ``(B,)``
    (the spread test), the reflection check when ``reflection`` and the quasi-affinity of the
    sample (every half, both ways), with their one-way inlier bounds on the pool.

    Args:
        x1, x2: ``(N, 2)`` the two images' points (reflection check).
        src_all, dst_all: ``(N, halves, 2)`` float64 pixels of every half.
        pool_src, pool_dst: ``(2, n)`` float32 x and y rows of the pool's first half.
        t2: squared threshold of the one-way bound, in the pool coordinates' units.

    Returns:
        ``(H, Hinv, sign, sign_inv, sample, ub)`` of the ``K`` survivors, in sample order:
        ``(K, halves, 3, 3)`` unit-norm homographies and adjugates, ``(K, halves)`` signs of
        the first sample point's ``w`` forward and backward, ``(K, 4)`` samples and ``(K,)``
        int64 one-way inlier counts.
    """
    K, H, Hinv, sign, sign_inv, smp, ub = KERNELS()["_hypotheses"](
        sample, ok, x1, x2, src_all, dst_all, bool(reflection), pool_src[0], pool_src[1],
        pool_dst[0], pool_dst[1], np.float32(t2))
    return H[:K], Hinv[:K], sign[:K], sign_inv[:K], smp[:K], ub[:K]


def inlier_masks(H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
                 pts: np.ndarray, t2: float, s2: float) -> np.ndarray:
    """``(K, n)`` bool: the squared error of each hypothesis (``H``, ``Hinv`` ``(K, halves,
    3, 3)``, signs ``(K, halves)``) on each match, times ``s2``, is at most ``t2`` in every
    half and direction, with ``w`` of the sample's sign (:func:`..scoring.inlier_masks`, the
    same decisions for the same hypotheses). ``pts`` ``(halves, 2, 2, n)``: per half, source
    then destination, x row then y row."""
    return KERNELS()["_inlier_masks"](H, Hinv, sign, sign_inv, pts, float(t2), float(s2))


def error_sq(H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
             pts: np.ndarray, s2: float) -> np.ndarray:
    """``(K, n)`` float64: the max over halves and directions of the squared transfer error,
    ``inf`` where ``w`` breaks the sample's sign, times ``s2`` (:func:`..scoring.error_sq`,
    the same bits); arguments as :func:`inlier_masks`."""
    return KERNELS()["_error_sq"](H, Hinv, sign, sign_inv, pts, float(s2))


def singular_value_ok(sample: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray,
                      min_sv: float) -> np.ndarray:
    """``(K,)`` bool: the Hartley-normalised minimal DLT system (``8 x 9``) of each sample
    ``(K, 4)`` (global indices) has its smallest singular value above ``min_sv`` in every
    half (:func:`..scoring.passes_singular_value_test`; the eigenvalues of ``A A^T`` from
    LAPACK as numpy's, the products summed in another order)."""
    return KERNELS()["_singular_value_ok"](sample, src_all, dst_all, float(min_sv))
