"""Compiled (numba) kernels of :mod:`..scoring` (and :mod:`..ransac`'s batch scoring and refit,
beside the helpers they share): one call per chain of numpy calls, the same decisions; the
homographies may differ from numpy's in the last bits."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit, jit_helpers


def _sign(v: float) -> float:
    """-1, 0 or 1 (0 for nan: a nan sign fails every sign test, as numpy's nan sign does)."""
    if v > 0:
        return 1.0
    if v < 0:
        return -1.0
    return 0.0


def _adjugate(e, out) -> None:
    """``out[9]`` = the adjugate of the row-major 3x3 ``e[9]``."""
    out[0] = e[4] * e[8] - e[5] * e[7]
    out[1] = e[2] * e[7] - e[1] * e[8]
    out[2] = e[1] * e[5] - e[2] * e[4]
    out[3] = e[5] * e[6] - e[3] * e[8]
    out[4] = e[0] * e[8] - e[2] * e[6]
    out[5] = e[2] * e[3] - e[0] * e[5]
    out[6] = e[3] * e[7] - e[4] * e[6]
    out[7] = e[1] * e[6] - e[0] * e[7]
    out[8] = e[0] * e[4] - e[1] * e[3]


def _normalised(e) -> bool:
    """Scale ``e[9]`` to unit Frobenius norm in place; whether all entries are finite."""
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


def _basis_map(px, py, A, lam, work):
    """Fill ``A[9]`` and ``lam[3]`` of :func:`..homography._basis_map`; returns ``det(P)``."""
    P = work[:9]
    adj = work[9:18]
    for c in range(3):
        P[c] = px[c]
        P[3 + c] = py[c]
        P[6 + c] = 1.0
    _adjugate(P, adj)
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
    """Signed doubled area of the triangle of points ``i, j, k`` of ``pts``."""
    ax = pts[j, 0] - pts[i, 0]
    ay = pts[j, 1] - pts[i, 1]
    bx = pts[k, 0] - pts[i, 0]
    by = pts[k, 1] - pts[i, 1]
    return ax * by - ay * bx


def _hypotheses(sample, ok, x1, x2, src_all, dst_all, reflection, X, Y, x2p, y2p, t2):
    """See :func:`hypotheses`; the first ``K`` rows of each output are valid."""
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
            _adjugate(A, adjA)
            for r in range(3):
                for c in range(3):
                    Hm[3 * r + c] = (Bm[3 * r] * adjA[c] + Bm[3 * r + 1] * adjA[3 + c]
                                     + Bm[3 * r + 2] * adjA[6 + c])
            if not _normalised(Hm):
                valid = False
            sl0, sl1, sl2 = _sign(lam[0]), _sign(lam[1]), _sign(lam[2])
            sm0, sm1, sm2 = _sign(mu[0]), _sign(mu[1]), _sign(mu[2])
            sdp, sdq = _sign(det_p), _sign(det_q)
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
            _adjugate(Hm, Hi)
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


def _transfer(h, X, Y, u, v):
    """``(e, w)`` of one point under row-major ``h[9]``, in :func:`..homography.transfer_error_sq`'s order."""
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


def _rows(H, sign, Hinv, sign_inv, k, scaled, out):
    """``out[2 * halves, 9]``: hypothesis ``k``'s forward and backward matrices, sign-scaled if ``scaled``."""
    for h in range(H.shape[1]):
        for e in range(9):
            f, b = H[k, h, e // 3, e % 3], Hinv[k, h, e // 3, e % 3]
            if scaled:
                f *= sign[k, h]
                b *= sign_inv[k, h]
            out[2 * h, e] = f
            out[2 * h + 1, e] = b


def _mask_row(hk, pts, t2, s2, out):
    """``out[n]``: whether each match is inside in every half and direction."""
    terms = hk.shape[0]
    for i in range(pts.shape[3]):
        inside = True
        for t in range(terms):
            h, d = t // 2, t % 2
            e, w = _transfer(hk[t], pts[h, d, 0, i], pts[h, d, 1, i],
                             pts[h, 1 - d, 0, i], pts[h, 1 - d, 1, i])
            if s2 != 1.0:
                e *= s2
            if not (e <= t2 and w > 0):
                inside = False
                break
        out[i] = inside


def _inlier_masks(H, Hinv, sign, sign_inv, pts, t2, s2):
    K = H.shape[0]
    terms = 2 * H.shape[1]
    n = pts.shape[3]
    out = np.zeros((K, n), dtype=np.bool_)
    hk = np.empty((terms, 9))
    for k in range(K):
        _rows(H, sign, Hinv, sign_inv, k, True, hk)
        _mask_row(hk, pts, t2, s2, out[k])
    return out


def _error_sq(H, Hinv, sign, sign_inv, pts, s2):
    K = H.shape[0]
    terms = 2 * H.shape[1]
    n = pts.shape[3]
    out = np.empty((K, n))
    hk = np.empty((terms, 9))
    for k in range(K):
        _rows(H, sign, Hinv, sign_inv, k, False, hk)
        for i in range(n):
            err = 0.0
            for t in range(terms):
                h, d = t // 2, t % 2
                e, w = _transfer(hk[t], pts[h, d, 0, i], pts[h, d, 1, i],
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


def _normalise4(pts, out):
    """Hartley-normalised copy ``out[4, 2]`` of ``pts[4, 2]``."""
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


def _sv_ok_one(sample, k, src_all, dst_all, min_sv, p, q, s, d, A) -> bool:
    """Whether sample ``k``'s minimal DLT system passes ``min_sv`` in every half (scratch arrays given)."""
    for h in range(src_all.shape[1]):
        for i in range(4):
            for c in range(2):
                p[i, c] = src_all[sample[k, i], h, c]
                q[i, c] = dst_all[sample[k, i], h, c]
        _normalise4(p, s)
        _normalise4(q, d)
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


def _singular_value_ok(sample, src_all, dst_all, min_sv):
    K = sample.shape[0]
    ok = np.ones(K, dtype=np.bool_)
    p = np.empty((4, 2))
    q = np.empty((4, 2))
    s = np.empty((4, 2))
    d = np.empty((4, 2))
    A = np.zeros((8, 9))
    for k in range(K):
        ok[k] = _sv_ok_one(sample, k, src_all, dst_all, min_sv, p, q, s, d, A)
    return ok


def _score_batch(ub, count0, have_best, n_req, z, H, Hinv, sign, sign_inv, sample, src_all,
                 dst_all, min_sv, pts, t2, s2):
    L = ub.shape[0]
    order = np.argsort(-ub, kind="mergesort")  # stable: the same order as numpy's
    n_buf = 0
    for p in range(min(2, z, L)):
        if ub[order[p]] >= n_req:
            n_buf += 1
    first = n_buf
    above = 0
    for p in range(L):
        if ub[p] > count0:
            above += 1
    first = max(first, above)
    reach = min(L, -(-first // 4) * 4)
    n = pts.shape[3]
    masks = np.empty((reach, n), dtype=np.bool_)
    events = np.empty(2 * reach + 1, dtype=np.int64)
    n_events = 0
    terms = 2 * H.shape[1]
    hk = np.empty((terms, 9))
    p4 = np.empty((4, 2))
    q4 = np.empty((4, 2))
    s4 = np.empty((4, 2))
    d4 = np.empty((4, 2))
    A = np.zeros((8, 9))
    kp = np.empty(4, dtype=np.int64)
    cnt = np.empty(4, dtype=np.int64)
    used = np.empty(4, dtype=np.bool_)
    count = count0
    best = -1
    scored = 0
    start = 0
    while start < L and (ub[order[start]] > count or start < n_buf):
        nk = 0
        for p in range(start, min(start + 4, L)):
            k = order[p]
            if ub[k] > 0 and _sv_ok_one(sample, k, src_all, dst_all, min_sv, p4, q4, s4, d4, A):
                _rows(H, sign, Hinv, sign_inv, k, True, hk)
                _mask_row(hk, pts, t2, s2, masks[p])
                c = 0
                for i in range(n):
                    if masks[p, i]:
                        c += 1
                kp[nk] = p
                cnt[nk] = c
                used[nk] = False
                nk += 1
        start += 4
        scored += nk
        for _ in range(nk):  # by count, descending; ties in position order (stable)
            j = -1
            for i in range(nk):
                if not used[i] and (j < 0 or cnt[i] > cnt[j]):
                    j = i
            used[j] = True
            if cnt[j] > count:
                if have_best:
                    events[n_events] = best  # -1: the best before this batch
                    n_events += 1
                best, count, have_best = kp[j], cnt[j], True
            elif cnt[j] > 0:
                events[n_events] = kp[j]
                n_events += 1
    return order, masks, events[:n_events], best, count, scored


def _normalising(pts, out, T):
    """Hartley normalisation of ``pts[M, 2]`` into ``out`` and the similarity ``T[3, 3]``."""
    M = pts.shape[0]
    cx = 0.0
    cy = 0.0
    for i in range(M):
        cx += pts[i, 0]
        cy += pts[i, 1]
    cx /= M
    cy /= M
    dist = 0.0
    for i in range(M):
        out[i, 0] = pts[i, 0] - cx
        out[i, 1] = pts[i, 1] - cy
        dist += np.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2)
    scale = np.sqrt(2.0) / max(dist / M, 1e-12)
    for i in range(M):
        out[i, 0] *= scale
        out[i, 1] *= scale
    T[:] = 0.0
    T[0, 0] = scale
    T[1, 1] = scale
    T[0, 2] = -scale * cx
    T[1, 2] = -scale * cy
    T[2, 2] = 1.0


def _refit(idx, src_all, dst_all, sample):
    nh = src_all.shape[1]
    M = idx.shape[0]
    H = np.empty((nh, 3, 3))
    Hinv = np.empty((nh, 3, 3))
    sign = np.empty(nh)
    sign_inv = np.empty(nh)
    p = np.empty((M, 2))
    q = np.empty((M, 2))
    s = np.empty((M, 2))
    d = np.empty((M, 2))
    T1 = np.empty((3, 3))
    T2 = np.empty((3, 3))
    row = np.empty(9)
    e = np.empty(9)
    adj = np.empty(9)
    for h in range(nh):
        for i in range(M):
            for c in range(2):
                p[i, c] = src_all[idx[i], h, c]
                q[i, c] = dst_all[idx[i], h, c]
        _normalising(p, s, T1)
        _normalising(q, d, T2)
        ata = np.zeros((9, 9))
        for i in range(M):
            x, y, u, v = s[i, 0], s[i, 1], d[i, 0], d[i, 1]
            for r in range(2):
                row[:] = 0.0
                if r == 0:
                    row[0] = x
                    row[1] = y
                    row[2] = 1.0
                    row[6] = -u * x
                    row[7] = -u * y
                    row[8] = -u
                else:
                    row[3] = x
                    row[4] = y
                    row[5] = 1.0
                    row[6] = -v * x
                    row[7] = -v * y
                    row[8] = -v
                for a in range(9):
                    if row[a] != 0.0:
                        for b in range(9):
                            ata[a, b] += row[a] * row[b]
        vecs = np.linalg.eigh(ata)[1]
        Hn = np.empty((3, 3))
        for a in range(9):
            Hn[a // 3, a % 3] = vecs[a, 0]  # the smallest eigenvalue's eigenvector
        for a in range(9):
            e[a] = T2[a // 3, a % 3]
        _adjugate(e, adj)
        Ht = np.empty((3, 3))
        for r in range(3):
            for c in range(3):
                Ht[r, c] = adj[3 * r] * Hn[0, c] + adj[3 * r + 1] * Hn[1, c] + adj[3 * r + 2] * Hn[2, c]
        for r in range(3):
            for c in range(3):
                e[3 * r + c] = Ht[r, 0] * T1[0, c] + Ht[r, 1] * T1[1, c] + Ht[r, 2] * T1[2, c]
        if not _normalised(e):
            return False, H, Hinv, sign, sign_inv
        _adjugate(e, adj)
        for direction in range(2):
            m = e if direction == 0 else adj
            pts = src_all if direction == 0 else dst_all
            first = 0.0
            for i in range(4):
                j = sample[i]
                w = m[6] * pts[j, h, 0] + m[7] * pts[j, h, 1] + m[8]
                sg = _sign(w)
                if i == 0:
                    if sg == 0.0:
                        return False, H, Hinv, sign, sign_inv
                    first = sg
                elif sg != first:
                    return False, H, Hinv, sign, sign_inv
            if direction == 0:
                sign[h] = first
            else:
                sign_inv[h] = first
        for a in range(9):
            H[h, a // 3, a % 3] = e[a]
            Hinv[h, a // 3, a % 3] = adj[a]
    return True, H, Hinv, sign, sign_inv


def _jit_all() -> dict[str, Any]:
    jit_helpers(globals(), (_sign, _adjugate, _normalised, _basis_map, _one_sign, _orientation, _transfer, _rows,
                            _mask_row, _normalise4, _sv_ok_one, _normalising))
    j = jit()
    return {f.__name__: j(f) for f in (_hypotheses, _inlier_masks, _error_sq, _singular_value_ok, _score_batch, _refit)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def hypotheses(sample: np.ndarray, ok: np.ndarray, x1: np.ndarray, x2: np.ndarray,
               src_all: np.ndarray, dst_all: np.ndarray, reflection: bool,
               pool_src: np.ndarray, pool_dst: np.ndarray, t2: float):
    """``(H, Hinv, sign, sign_inv, sample, ub)`` of the samples ``(B, 4)`` that pass ``ok``, the
    reflection check and quasi-affinity, with their one-way inlier bounds on the pool."""
    K, H, Hinv, sign, sign_inv, smp, ub = KERNELS()["_hypotheses"](
        sample, ok, x1, x2, src_all, dst_all, bool(reflection), pool_src[0], pool_src[1],
        pool_dst[0], pool_dst[1], np.float32(t2))
    return H[:K], Hinv[:K], sign[:K], sign_inv[:K], smp[:K], ub[:K]


def inlier_masks(H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
                 pts: np.ndarray, t2: float, s2: float) -> np.ndarray:
    """``(K, n)`` bool: every half and direction's squared error times ``s2`` is at most ``t2``,
    with ``w`` of the sample's sign. ``pts`` ``(halves, 2, 2, n)``: source then destination, x then
    y."""
    return KERNELS()["_inlier_masks"](H, Hinv, sign, sign_inv, pts, float(t2), float(s2))


def error_sq(H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
             pts: np.ndarray, s2: float) -> np.ndarray:
    """``(K, n)`` max squared transfer error over halves and directions (``inf`` where ``w`` breaks
    the sign), times ``s2``."""
    return KERNELS()["_error_sq"](H, Hinv, sign, sign_inv, pts, float(s2))


def singular_value_ok(sample: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray,
                      min_sv: float) -> np.ndarray:
    """``(K,)`` bool: each sample's normalised minimal DLT system passes ``min_sv`` in every half."""
    return KERNELS()["_singular_value_ok"](sample, src_all, dst_all, float(min_sv))


def score_batch(ub: np.ndarray, count: int, have_best: bool, n_req: int, z: int,
                H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
                sample: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray, min_sv: float,
                pts: np.ndarray, t2: float, s2: float):
    """The full scoring of one batch in one call, as ``ransac._score_batch``: ``(order, masks,
    events, best, count, scored)``."""
    return KERNELS()["_score_batch"](ub, int(count), bool(have_best), int(n_req), int(z),
                                       H, Hinv, sign, sign_inv, sample, src_all, dst_all,
                                       float(min_sv), pts, float(t2), float(s2))


def refit(idx: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray, sample: np.ndarray):
    """Least-squares normalised DLT of every half on the matches ``idx`` (``M >= 5``), checked
    against the sample's quasi-affine signs. Returns ``(ok, H, Hinv, sign, sign_inv)``."""
    return KERNELS()["_refit"](idx, src_all, dst_all, sample)
