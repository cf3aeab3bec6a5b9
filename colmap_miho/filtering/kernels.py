"""Compiled (numba) kernels of a RANSAC batch: each replaces a chain of small numpy calls
with one call, which is what a batch on a pool of a few hundred matches costs.

- :func:`spread_ok`: the spread test of minimal samples (:func:`.sampling.spread_ok`);
- :func:`hypotheses`: reflection check, closed-form 4-point solver with the sample's
  quasi-affine signs, adjugates and the one-way float32 inlier bound on the pool, fused
  (:func:`.scoring.hypotheses_from_samples` then :func:`.scoring.one_way_count`);
- :func:`draw_local` and :func:`pool_neighbours`: the local draws and the pool's neighbour
  lists (``Sampler``); :func:`draw_batch`: a batch's local draws with the searches they need
  (the problem's candidates, the pool's lists), in one call;
- :func:`singular_value_ok`, :func:`inlier_masks`, :func:`error_sq`: full scoring
  (:mod:`.scoring`); :func:`score_batch`: a batch's whole full scoring (the first two) and
  its search's choices, in one call;
  :func:`refit`: the least-squares refit of a run's best model;
- :func:`rotation_counts`: the rotation fix's pair counts (:func:`.miho.choose_rotation`);
- :func:`greedy_cover`: the choice of a run's top-z buffer (``ransac._greedy_buffer``).

The numpy functions stay the reference (and the path of the torch scoring on CUDA); the tests
check each kernel against them. The spread test, the draws, the neighbour lists, the masks,
the errors and the rotation counts are the same decisions / bits for the same inputs; the
solver, the singular values and the refit add their products in a fixed order where numpy's
matmul (BLAS) may fuse or reorder them, so homographies can differ in the last bits, and
with them, rarely, a borderline decision.

The kernels compile on first use (:mod:`colmap_miho.compiled`); :func:`.preload.warm` loads
them ahead (:func:`loaded` says whether they are). This module imports nothing else of the
filter: the filter's modules import it.
:class:`NearestGrid` is the compiled path's neighbour search for local sampling (the numpy
path keeps scipy's k-d tree).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..compiled import Kernels, jit, jit_helpers


def _sign(v: float) -> float:
    """-1, 0 or 1 (0 for nan: a nan sign fails every sign test, as numpy's nan sign does)."""
    if v > 0:
        return 1.0
    if v < 0:
        return -1.0
    return 0.0


def _adjugate(e, out) -> None:
    """``out[9]`` = the adjugate of the row-major 3x3 ``e[9]`` (the products and differences
    of :func:`.homography.adjugate`)."""
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


def _basis_map(px, py, A, lam, work):
    """Fill ``A[9]`` (row-major ``P diag(lam)``) and ``lam[3]`` for the 4 points ``px[4]``,
    ``py[4]`` (:func:`.homography._basis_map`); returns ``det(P)``. ``work[18]`` scratch."""
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


def _spread_ok(spread_xy, sample, t2):
    """``(B,)`` bool: see :func:`spread_ok`."""
    B = sample.shape[0]
    sets = spread_xy.shape[1]
    ok = np.ones(B, dtype=np.bool_)
    for b in range(B):
        good = True
        for i in range(3):
            a = sample[b, i]
            for j in range(i + 1, 4):
                c = sample[b, j]
                for s in range(sets):
                    dx = spread_xy[0, s, a] - spread_xy[0, s, c]
                    dy = spread_xy[1, s, a] - spread_xy[1, s, c]
                    dx *= dx
                    dy *= dy
                    dx += dy
                    if not dx >= t2:
                        good = False
                        break
                if not good:
                    break
            if not good:
                break
        ok[b] = good
    return ok


_TRIANGLES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


def _orientation(pts, i, j, k) -> float:
    """Signed doubled area of the triangle of points ``i, j, k`` of ``pts`` ``(N, 2)``
    (:func:`.homography.triangle_orientations`)."""
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


def _draw_local(nb, keys, seeds, spread_x, spread_y, t2):
    """See :func:`draw_local`."""
    return _draw_local_rows(nb, keys, seeds, spread_x, spread_y, t2)


def _draw_local_rows(nb, keys, seeds, spread_x, spread_y, t2):
    """See :func:`draw_local`."""
    L, k = nb.shape
    sets = spread_x.shape[0]
    out = np.empty((L, 3), dtype=np.int64)
    free = np.empty(k, dtype=np.bool_)
    for r in range(L):
        for c in range(k):
            free[c] = nb[r, c] >= 0
        for j in range(3):
            best = -2.0
            at = 0
            for c in range(k):
                key = keys[j, r, c] if free[c] else -1.0
                if key > best:
                    best = key
                    at = c
            if not free[at]:
                out[r, j] = seeds[r]
                # nothing is free: later picks find nothing either
                for jj in range(j + 1, 3):
                    out[r, jj] = seeds[r]
                break
            pick = nb[r, at]
            out[r, j] = pick
            if j < 2:
                for c in range(k):
                    if not free[c]:
                        continue
                    q = nb[r, c]
                    for s in range(sets):
                        dx = spread_x[s, q] - spread_x[s, pick]
                        dy = spread_y[s, q] - spread_y[s, pick]
                        dx *= dx
                        dy *= dy
                        dx += dy
                        if not dx >= t2:
                            free[c] = False
                            break
    return out


def _transfer(h, X, Y, u, v):
    """``(e, w)``: squared transfer error of the point ``(X, Y)`` to ``(u, v)`` under the
    row-major ``h[9]``, and its ``w`` (:func:`.homography.transfer_error_sq`'s operations, in
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


def _rows(H, sign, Hinv, sign_inv, k, scaled, out):
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


def _mask_row(hk, pts, t2, s2, out):
    """``out[n]``: whether each match is inside under the sign-scaled matrices ``hk``
    ``(2 * halves, 9)`` (:func:`_rows`), every half and direction (:func:`inlier_masks`)."""
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
    """See :func:`inlier_masks`."""
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
    """See :func:`error_sq`."""
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


def _far(sx, sy, a, b, t2) -> bool:
    """Matches ``a`` and ``b`` are at least ``sqrt(t2)`` apart in every set of ``sx``, ``sy``
    ``(sets, n)`` (:func:`.sampling.apart_sets`' operations)."""
    for s in range(sx.shape[0]):
        dx = sx[s, a] - sx[s, b]
        dy = sy[s, a] - sy[s, b]
        dx *= dx
        dy *= dy
        dx += dy
        if not dx >= t2:
            return False
    return True


def _push_nearest(best_d, best_j, filled, d, j) -> int:
    """Candidate ``j`` at squared distance ``d`` into the sorted buffers ``best_d`` /
    ``best_j`` (q = their length; ``filled`` entries used), nearest first, ties by index;
    returns the new ``filled``."""
    q = best_d.shape[0]
    if filled == q and not (d < best_d[q - 1] or (d == best_d[q - 1] and j < best_j[q - 1])):
        return filled
    at = filled if filled < q else q - 1
    while at > 0 and (best_d[at - 1] > d or (best_d[at - 1] == d and best_j[at - 1] > j)):
        best_d[at] = best_d[at - 1]
        best_j[at] = best_j[at - 1]
        at -= 1
    best_d[at] = d
    best_j[at] = j
    return filled + 1 if filled < q else filled


def _neighbours(todo, cand, far, pos, feats, sx, sy, t2, k, q, pool, lists, listed):
    """See :func:`pool_neighbours`."""
    return _neighbour_rows(todo, cand, far, False, pos, feats, sx, sy, t2, k, q, pool, lists,
                           listed)


def _neighbour_rows(todo, cand, far, by_match, pos, feats, sx, sy, t2, k, q, pool, lists,
                    listed):
    """:func:`pool_neighbours`; with ``by_match`` the candidates ``cand``, ``far`` are the
    problem's tables ``(N, c)``, read at each row's global index, else ``(m, c)`` rows."""
    m = todo.shape[0]
    n = feats.shape[0]
    dims = feats.shape[1]
    nb = np.full((m, k), -1, dtype=np.int64)
    best_d = np.empty(q)
    best_j = np.empty(q, dtype=np.int64)
    # the exhaustive search's coordinates, one contiguous row per dimension, and the
    # squared distances of one match to every pool match (made on the first search)
    cols = np.empty((0, n))
    dist = np.empty(n)
    for r in range(m):
        a_all = pool[todo[r]]
        if listed[a_all]:
            kept = True
            for c in range(k):
                if pos[lists[a_all, c]] < 0:
                    kept = False
                    break
            if kept:
                for c in range(k):
                    nb[r, c] = pos[lists[a_all, c]]
                continue
        cnt = 0
        cr = a_all if by_match else r
        for c in range(cand.shape[1]):
            g = cand[cr, c]
            if g < 0 or not far[cr, c]:
                continue
            p = pos[g]
            if p < 0:
                continue
            nb[r, cnt] = p
            cnt += 1
            if cnt == k:
                break
        if cnt == k:
            _keep_list(nb, r, pool, lists, listed, a_all)
            continue
        # Too few left in the pool: the q nearest pool matches (the first is the match
        # itself), nearest first, ties by position.
        a = todo[r]
        if cols.shape[0] == 0:
            cols = np.ascontiguousarray(feats.T)
        # the distances dimension by dimension over contiguous rows (the sum of squares in
        # the order of the dimensions, as scipy's k-d tree sums it)
        dist[:] = 0.0
        for e in range(dims):
            fa = feats[a, e]
            col = cols[e]
            for j in range(n):
                t = col[j] - fa
                dist[j] += t * t
        filled = 0
        for j in range(n):
            d = dist[j]
            # in the order of j a later candidate loses ties: only a nearer one enters
            if filled == q and not d < best_d[q - 1]:
                continue
            filled = _push_nearest(best_d, best_j, filled, d, j)
        cnt = 0
        for c in range(1, filled):
            j = best_j[c]
            if _far(sx, sy, j, a, t2):
                nb[r, cnt] = j
                cnt += 1
                if cnt == k:
                    break
        for c in range(cnt, k):
            nb[r, c] = -1
        if cnt == k:
            _keep_list(nb, r, pool, lists, listed, a_all)
        else:
            listed[a_all] = False
    return nb


def _keep_list(nb, r, pool, lists, listed, a):
    """Keep row ``r`` of ``nb`` (a full list, pool positions) as match ``a``'s list in
    ``lists`` (global indices) for the pools to come."""
    for c in range(nb.shape[1]):
        lists[a, c] = pool[nb[r, c]]
    listed[a] = True


def _normalise4(pts, out):
    """Hartley-normalised copy ``out[4, 2]`` of the 4 points ``pts[4, 2]``
    (:func:`.homography._normalised`)."""
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
    """Whether sample ``k``'s normalised minimal DLT system has its smallest singular value
    above ``min_sv`` in every half (:func:`singular_value_ok`); ``p``, ``q``, ``s``, ``d``
    ``(4, 2)`` and ``A`` ``(8, 9)`` (zero where no entry is written) scratch."""
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
    """See :func:`singular_value_ok`."""
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
    """See :func:`score_batch`."""
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
    """Hartley normalisation of ``pts[M, 2]``: ``out[M, 2]`` the normalised points and
    ``T[3, 3]`` the similarity (:func:`.homography.normalise_points`)."""
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
    """See :func:`refit`."""
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


def _rotation_counts(dx1, dx2, lo, hi, rows):
    """See :func:`rotation_counts`."""
    C = rows.shape[0]
    P = dx1.shape[1]
    scores = np.zeros(C, dtype=np.int64)
    differ = np.zeros(C, dtype=np.int64)
    first = np.zeros(P, dtype=np.bool_)
    x1, y1 = dx1[0], dx1[1]
    for c in range(C):
        # each row of the linear part has one nonzero entry, +-1: the coordinate
        # dx1 + r0 dx2[0] + r1 dx2[1] is dx1 + (that entry) x (that coordinate of dx2)
        k0 = 0 if rows[c, 0, 0] != 0.0 else 1
        k1 = 0 if rows[c, 1, 0] != 0.0 else 1
        g0, g1 = rows[c, 0, k0], rows[c, 1, k1]
        a0, a1 = dx2[k0], dx2[k1]
        sc = 0
        df = 0
        for p in range(P):
            v0 = x1[p] + g0 * a0[p]
            v1 = y1[p] + g1 * a1[p]
            sq = v0 * v0
            sq += v1 * v1
            dm = np.sqrt(sq) / 2
            inside = dm >= lo[p] and dm <= hi[p]
            if c == 0:
                first[p] = inside
            sc += inside
            df += inside != first[p]
        scores[c] = sc
        differ[c] = df
    return scores, differ


def _greedy_cover(masks, covered, z):
    """See :func:`greedy_cover`."""
    C, n = masks.shape
    cov = covered.copy()
    free = np.ones(C, dtype=np.bool_)
    chosen = np.empty(min(z, C), dtype=np.int64)
    m = 0
    for _ in range(min(z, C)):
        best, at = 0, -1
        for c in range(C):
            if not free[c]:
                continue
            gain = 0
            for i in range(n):
                if masks[c, i] and not cov[i]:
                    gain += 1
            if gain > best:
                best, at = gain, c
        if at < 0:
            break
        chosen[m] = at
        m += 1
        free[at] = False
        for i in range(n):
            if masks[at, i]:
                cov[i] = True
    return chosen[:m]


def _nearest(feats, todo, q, x0, y0, cell, nx, ny, start, members):
    """See :meth:`NearestGrid.query`."""
    return _nearest_rows(feats, todo, q, x0, y0, cell, nx, ny, start, members)


def _nearest_rows(feats, todo, q, x0, y0, cell, nx, ny, start, members):
    """See :meth:`NearestGrid.query`."""
    m = todo.shape[0]
    dims = feats.shape[1]
    out = np.empty((m, q), dtype=np.int64)
    best_d = np.empty(q)
    best_j = np.empty(q, dtype=np.int64)
    for r in range(m):
        a = todo[r]
        ax, ay = feats[a, 0], feats[a, 1]
        cx = min(max(int((ax - x0) / cell), 0), nx - 1)
        cy = min(max(int((ay - y0) / cell), 0), ny - 1)
        filled = 0
        ring = 0
        while True:
            for gy in range(cy - ring, cy + ring + 1):
                if gy < 0 or gy >= ny:
                    continue
                edge = gy == cy - ring or gy == cy + ring
                step = 1 if edge else 2 * ring
                gx = cx - ring
                while gx <= cx + ring:
                    if 0 <= gx < nx:
                        c = gy * nx + gx
                        for t in range(start[c], start[c + 1]):
                            j = members[t]
                            d = 0.0
                            for e in range(dims):
                                v = feats[j, e] - feats[a, e]
                                d += v * v
                            filled = _push_nearest(best_d, best_j, filled, d, j)
                    gx += step if ring > 0 else 1
            if ring >= nx and ring >= ny:
                break
            if filled == q:
                # every point not searched yet lies outside the searched square of cells
                margin = min(ax - (x0 + (cx - ring) * cell), x0 + (cx + ring + 1) * cell - ax,
                             ay - (y0 + (cy - ring) * cell), y0 + (cy + ring + 1) * cell - ay)
                if margin > 0 and margin * margin > best_d[q - 1]:
                    break
            ring += 1
        for c in range(q):
            out[r, c] = best_j[c]
    return out


def _search_needed(need, pool, pos, nb, known, cand, far, cknown, by_match, sx_all, sy_all,
                   feats_all, x0, y0, cell, nx, ny, start, members, pool_feats, sx, sy, t2, k,
                   q, lists, listed):
    """Search the neighbour lists ``nb`` of the pool positions where ``need`` ``(n,)``, in
    ascending order, and mark them ``known`` (:func:`draw_batch`'s search; its arguments)."""
    n = pool.shape[0]
    m = 0
    for p in range(n):
        if need[p]:
            m += 1
    if m:
        todo = np.empty(m, dtype=np.int64)
        m = 0
        for p in range(n):
            if need[p]:
                todo[m] = p
                m += 1
        if by_match:
            # the problem's candidates of the matches not searched yet (LocalCandidates.get)
            new = np.empty(m, dtype=np.int64)
            c_new = 0
            for i in range(m):
                g = pool[todo[i]]
                if not cknown[g]:
                    new[c_new] = g
                    c_new += 1
            qc = cand.shape[1]
            if c_new and qc:
                found = _nearest_rows(feats_all, new[:c_new], qc + 1, x0, y0, cell, nx, ny,
                                      start, members)
                for i in range(c_new):
                    g = new[i]
                    for c in range(qc):
                        j = found[i, c + 1]
                        cand[g, c] = j
                        far[g, c] = _far(sx_all, sy_all, j, g, t2)
            for i in range(c_new):
                cknown[new[i]] = True
        rows = _neighbour_rows(todo, cand, far, by_match, pos, pool_feats, sx, sy, t2, k, q,
                               pool, lists, listed)
        for i in range(m):
            for c in range(k):
                nb[todo[i], c] = rows[i, c]
            known[todo[i]] = True


def _need_of(probes, known, n, all_at_once):
    """``(n,)`` bool: the pool positions whose neighbour lists a draw or a probe of the
    positions ``probes`` needs searched: those of ``probes`` not ``known`` yet, or every
    position of a pool with ``all_at_once`` that has none searched yet."""
    fresh = True
    for p in range(n):
        if known[p]:
            fresh = False
            break
    need = np.zeros(n, dtype=np.bool_)
    if all_at_once and fresh:
        need[:] = True
    else:
        for i in range(probes.shape[0]):
            if not known[probes[i]]:
                need[probes[i]] = True
    return need


def _local_fraction(mask, rows, pool, pos, nb, known, all_at_once, cand, far, cknown,
                    by_match, sx_all, sy_all, feats_all, x0, y0, cell, nx, ny, start, members,
                    pool_feats, sx, sy, t2, k, q, lists, listed):
    """See :func:`local_fraction`."""
    n = pool.shape[0]
    m = rows.shape[0]
    probe = np.empty(m, dtype=np.int64)
    r = 0
    c = 0
    for p in range(n):  # the inliers' positions at the chosen ranks (ascending)
        if mask[p]:
            while r < m and rows[r] == c:
                probe[r] = p
                r += 1
            c += 1
    need = _need_of(probe, known, n, all_at_once)
    _search_needed(need, pool, pos, nb, known, cand, far, cknown, by_match, sx_all, sy_all,
                   feats_all, x0, y0, cell, nx, ny, start, members, pool_feats, sx, sy, t2, k,
                   q, lists, listed)
    valid = 0
    inside = 0
    for i in range(m):
        for j in range(k):
            v = nb[probe[i], j]
            if v >= 0:
                valid += 1
                if mask[v]:
                    inside += 1
    return valid, inside


def _draw_batch(seeds, others, local, keys, pool, pos, nb, known, all_at_once, cand, far,
                cknown, by_match, sx_all, sy_all, feats_all, x0, y0, cell, nx, ny, start,
                members, pool_feats, sx, sy, t2, k, q, lists, listed):
    """See :func:`draw_batch`."""
    n = pool.shape[0]
    size = seeds.shape[0]
    L = local.shape[0]
    if L:
        # the seeds' neighbour lists not searched yet (all of a small pool at its first draw)
        probes = np.empty(L, dtype=np.int64)
        for i in range(L):
            probes[i] = seeds[local[i]]
        need = _need_of(probes, known, n, all_at_once)
        _search_needed(need, pool, pos, nb, known, cand, far, cknown, by_match, sx_all, sy_all,
                       feats_all, x0, y0, cell, nx, ny, start, members, pool_feats, sx, sy, t2,
                       k, q, lists, listed)
        lnb = np.empty((L, k), dtype=np.int64)
        lseeds = np.empty(L, dtype=np.int64)
        for i in range(L):
            lseeds[i] = seeds[local[i]]
            for c in range(k):
                lnb[i, c] = nb[lseeds[i], c]
        picked = _draw_local_rows(lnb, keys, lseeds, sx, sy, t2)
        for i in range(L):
            for j in range(3):
                others[local[i], j] = picked[i, j]
    out = np.empty((size, 4), dtype=np.int64)
    for b in range(size):
        out[b, 0] = pool[seeds[b]]
        for j in range(3):
            out[b, j + 1] = pool[others[b, j]]
    return out


def _jit_all() -> dict[str, Any]:
    """Jit every kernel and the helpers they call (numpy's error model: a division by zero
    gives inf / nan, and those entries fail the sign test)."""
    jit_helpers(globals(), (_sign, _adjugate, _normalised, _basis_map, _one_sign, _orientation, _transfer,
                            _rows, _far, _mask_row, _sv_ok_one, _normalise4, _normalising, _push_nearest,
                            _keep_list, _draw_local_rows, _neighbour_rows, _nearest_rows, _search_needed,
                            _need_of))
    j = jit()
    return {f.__name__: j(f) for f in (_spread_ok, _hypotheses, _draw_local, _inlier_masks,
                                       _error_sq, _neighbours, _singular_value_ok, _refit,
                                       _rotation_counts, _greedy_cover, _nearest,
                                       _draw_batch, _score_batch,
                                       _local_fraction)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
_compiled = Kernels(_jit_all)


def loaded() -> bool:
    """Whether the kernels are loaded in this process (compiled or read from numba's cache)."""
    return _compiled.loaded


def spread_ok(spread_xy: np.ndarray, sample: np.ndarray, t2: float) -> np.ndarray:
    """``(B,)`` bool: the 4 matches of each minimal sample ``(B, 4)`` (global indices) are
    pairwise at least ``sqrt(t2)`` pixels apart in every spread set; ``spread_xy``
    ``(2, sets, N)`` float64 (``Problem.spread_xy``)."""
    return _compiled()["_spread_ok"](spread_xy, sample, float(t2))


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
    K, H, Hinv, sign, sign_inv, smp, ub = _compiled()["_hypotheses"](
        sample, ok, x1, x2, src_all, dst_all, bool(reflection), pool_src[0], pool_src[1],
        pool_dst[0], pool_dst[1], np.float32(t2))
    return H[:K], Hinv[:K], sign[:K], sign_inv[:K], smp[:K], ub[:K]


def draw_local(nb: np.ndarray, keys: np.ndarray, seeds: np.ndarray, spread_x: np.ndarray,
               spread_y: np.ndarray, t2: float) -> np.ndarray:
    """``(L, 3)`` pool positions drawn one by one among each seed's neighbours ``nb``
    ``(L, k)`` (pool positions, -1 = none): the free neighbour of the largest key ``keys[j]``
    ``(3, L, k)`` uniform in [0, 1), then only those at least ``sqrt(t2)`` from it in every
    spread set ``spread_x``, ``spread_y`` ``(sets, n)`` stay free; the seed where none is
    free."""
    return _compiled()["_draw_local"](nb, keys, seeds, spread_x, spread_y, float(t2))


def draw_batch(seeds: np.ndarray, others: np.ndarray, local: np.ndarray, keys: np.ndarray,
               pool: np.ndarray, pos: np.ndarray, nb: np.ndarray, known: np.ndarray,
               all_at_once: bool, cand: np.ndarray, far: np.ndarray, cknown: np.ndarray,
               grid: NearestGrid | None, sx_all: np.ndarray, sy_all: np.ndarray,
               pool_feats: np.ndarray, sx: np.ndarray, sy: np.ndarray, t2: float, k: int,
               q: int, lists: np.ndarray, listed: np.ndarray) -> np.ndarray:
    """``(B, 4)`` global match indices of one batch of local sampling (``Sampler.draw``
    with the compiled kernels, the same samples): the seeds ``seeds`` ``(B,)`` with the
    others ``others`` ``(B, 3)`` (pool positions, uniform draws), where the samples
    ``local`` ``(L,)`` take theirs among the seed's neighbours by the keys ``keys`` ``(3, L,
    k)`` (:func:`draw_local`).

    The neighbour lists ``nb`` ``(n, k)`` (pool positions) of the local seeds not ``known``
    ``(n,)`` yet are searched first (:func:`pool_neighbours`; every pool match at the
    first search when ``all_at_once``), both updated in place. ``grid``: the problem's
    :class:`NearestGrid`, whose candidates fill ``cand``, ``far`` ``(N, c)`` where
    ``cknown`` ``(N,)`` is False (updated in place; ``LocalCandidates``' tables), ``None``
    for a problem searched without candidates. ``sx_all``, ``sy_all`` ``(sets, N)``: the
    problem's spread sets; ``pool`` ``(n,)``, ``pos``, ``pool_feats``, ``sx``, ``sy``,
    ``t2``, ``k``, ``q``, ``lists``, ``listed`` as :func:`pool_neighbours`.
    """
    if grid is None:
        empty = np.empty(0, dtype=np.int64)
        x0 = y0 = cell = 0.0
        nx = ny = 0
        feats_all, start, members = np.empty((0, 4)), empty, empty
        cand, far = np.empty((0, 0), dtype=np.int64), np.empty((0, 0), dtype=np.bool_)
    else:
        x0, y0, cell, nx, ny = grid.x0, grid.y0, grid.cell, grid.nx, grid.ny
        feats_all, start, members = grid.feats, grid.start, grid.members
    return _compiled()["_draw_batch"](
        seeds, others, local, keys, pool, pos, nb, known, bool(all_at_once), cand, far,
        cknown, grid is not None, sx_all, sy_all, feats_all, float(x0), float(y0), float(cell),
        int(nx), int(ny), start, members, pool_feats, sx, sy, float(t2), int(k), int(q), lists,
        listed)


def local_fraction(mask: np.ndarray, rows: np.ndarray, pool: np.ndarray, pos: np.ndarray,
                   nb: np.ndarray, known: np.ndarray, all_at_once: bool, cand: np.ndarray,
                   far: np.ndarray, cknown: np.ndarray, grid: NearestGrid | None,
                   sx_all: np.ndarray, sy_all: np.ndarray, pool_feats: np.ndarray,
                   sx: np.ndarray, sy: np.ndarray, t2: float, k: int, q: int,
                   lists: np.ndarray, listed: np.ndarray) -> tuple[int, int]:
    """``(valid, inside)``: of the neighbours (pool positions in ``nb`` ``(n, k)``, -1 =
    none) of the inliers ``mask`` ``(n,)`` at the ranks ``rows`` (ascending, among the
    inliers in pool order), how many there are and how many are inliers
    (``Sampler.local_inlier_fraction``); the lists not ``known`` yet are searched first, as
    :func:`draw_batch` searches a batch's seeds (its arguments, updated in place)."""
    grid_args = _grid_args(grid, cand, far)
    return _compiled()["_local_fraction"](
        mask, rows, pool, pos, nb, known, bool(all_at_once), *grid_args[:2], cknown,
        grid is not None, sx_all, sy_all, *grid_args[2:], pool_feats, sx, sy, float(t2),
        int(k), int(q), lists, listed)


def _grid_args(grid: NearestGrid | None, cand: np.ndarray, far: np.ndarray) -> tuple:
    """``(cand, far, feats, x0, y0, cell, nx, ny, start, members)`` of the compiled search
    for ``grid`` (empty tables and grid for a problem searched without candidates)."""
    if grid is None:
        empty = np.empty(0, dtype=np.int64)
        return (np.empty((0, 0), dtype=np.int64), np.empty((0, 0), dtype=np.bool_),
                np.empty((0, 4)), 0.0, 0.0, 0.0, 0, 0, empty, empty)
    return (cand, far, grid.feats, float(grid.x0), float(grid.y0), float(grid.cell),
            int(grid.nx), int(grid.ny), grid.start, grid.members)


def inlier_masks(H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
                 pts: np.ndarray, t2: float, s2: float) -> np.ndarray:
    """``(K, n)`` bool: the squared error of each hypothesis (``H``, ``Hinv`` ``(K, halves,
    3, 3)``, signs ``(K, halves)``) on each match, times ``s2``, is at most ``t2`` in every
    half and direction, with ``w`` of the sample's sign (:func:`.scoring.inlier_masks`, the
    same decisions for the same hypotheses). ``pts`` ``(halves, 2, 2, n)``: per half, source
    then destination, x row then y row."""
    return _compiled()["_inlier_masks"](H, Hinv, sign, sign_inv, pts, float(t2), float(s2))


def error_sq(H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
             pts: np.ndarray, s2: float) -> np.ndarray:
    """``(K, n)`` float64: the max over halves and directions of the squared transfer error,
    ``inf`` where ``w`` breaks the sample's sign, times ``s2`` (:func:`.scoring.error_sq`,
    the same bits); arguments as :func:`inlier_masks`."""
    return _compiled()["_error_sq"](H, Hinv, sign, sign_inv, pts, float(s2))


def pool_neighbours(todo: np.ndarray, cand: np.ndarray, far: np.ndarray, pos: np.ndarray,
                    feats: np.ndarray, spread_x: np.ndarray, spread_y: np.ndarray, t2: float,
                    k: int, q: int, pool: np.ndarray, lists: np.ndarray,
                    listed: np.ndarray) -> np.ndarray:
    """``(m, k)`` pool positions of the nearest pool matches at least ``sqrt(t2)`` from each
    of the pool positions ``todo`` ``(m,)`` in every spread set, -1 padded
    (``Sampler.neighbours``).

    The first ``k`` of the problem-wide candidates ``cand`` ``(m, c)`` (global indices,
    nearest first, -1 = none) that are ``far`` ``(m, c)`` enough and in the pool (``pos``
    ``(N,)``: global index -> pool position, -1 outside); where fewer than ``k``, the first
    ``k`` far enough among the ``q - 1`` nearest pool matches in ``feats`` ``(n, dims)``
    (exhaustive search, ties by pool position). ``spread_x``, ``spread_y``: ``(sets, n)``
    of the pool; ``pool`` ``(n,)`` its global indices, ascending.

    ``lists`` ``(N, k)`` (global indices) and ``listed`` ``(N,)`` bool carry the full lists
    (k neighbours) found for earlier pools that contain this one, and are updated: a match
    whose kept list lies wholly in the pool has that list again, without a search. The
    same list, because the pool only lost matches since: every pool match nearer than a
    listed one (in the candidates' order, or in distance and position) was nearer in the
    earlier pool, where it was either listed or not far enough; and the listed ones keep
    their order and lie no deeper in the ``q`` nearest. The caller drops the lists
    (``listed[:] = False``) when the pool is not a subset of the earlier ones.
    """
    return _compiled()["_neighbours"](todo, cand, far, pos, feats, spread_x, spread_y,
                                      float(t2), int(k), int(q), pool, lists, listed)


def singular_value_ok(sample: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray,
                      min_sv: float) -> np.ndarray:
    """``(K,)`` bool: the Hartley-normalised minimal DLT system (``8 x 9``) of each sample
    ``(K, 4)`` (global indices) has its smallest singular value above ``min_sv`` in every
    half (:func:`.scoring.passes_singular_value_test`; the eigenvalues of ``A A^T`` from
    LAPACK as numpy's, the products summed in another order)."""
    return _compiled()["_singular_value_ok"](sample, src_all, dst_all, float(min_sv))


def score_batch(ub: np.ndarray, count: int, have_best: bool, n_req: int, z: int,
                H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
                sample: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray, min_sv: float,
                pts: np.ndarray, t2: float, s2: float):
    """The full scoring of one batch of hypotheses in one call (``ransac._score_batch``'s
    loop and its search's choices, the same decisions): in descending order of their
    one-way bounds ``ub`` ``(K,)`` (stable), groups of 4 are scored (bound > 0,
    :func:`singular_value_ok`, then :func:`inlier_masks`) while a bound can beat the best count
    (``count`` at the start) or a group holds one of the batch's two strongest with at
    least ``n_req`` possible inliers (at most ``z``); within a group the hypotheses are
    taken by count, descending: one above the best becomes the best (the best it replaces,
    if ``have_best``, becomes a candidate), another with inliers a candidate.

    Returns ``(order, masks, events, best, count, scored)``: the order ``(K,)`` (position
    -> hypothesis row), the masks ``(R, n)`` by position (rows of scored positions only),
    the candidates ``(E,)`` in the order they arose (positions; -1: the best from before the
    batch), the new best's position (-1: unchanged), the best count and the number of
    hypotheses scored. ``H``, ``Hinv``, signs and ``sample`` ``(K, ...)``: the hypotheses;
    ``src_all``, ``dst_all``, ``min_sv`` as :func:`singular_value_ok`; ``pts``, ``t2``,
    ``s2`` as :func:`inlier_masks`.
    """
    return _compiled()["_score_batch"](ub, int(count), bool(have_best), int(n_req), int(z),
                                       H, Hinv, sign, sign_inv, sample, src_all, dst_all,
                                       float(min_sv), pts, float(t2), float(s2))


def refit(idx: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray, sample: np.ndarray):
    """Least-squares normalised DLT of every half on the matches ``idx`` ``(M,)`` (global,
    ``M >= 5``), checked against the quasi-affine signs of the minimal ``sample`` ``(4,)``
    (``ransac._refit``: the smallest eigenvector of ``A^T A`` by LAPACK, as numpy's, the
    products summed in another order).

    Returns ``(ok, H, Hinv, sign, sign_inv)``: whether the fit is finite and keeps one
    nonzero sign of ``w`` on the sample's 4 points (every half, both ways), ``(halves, 3,
    3)`` unit-norm homographies and adjugates and ``(halves,)`` signs.
    """
    return _compiled()["_refit"](idx, src_all, dst_all, sample)


def rotation_counts(dx1: np.ndarray, dx2: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pair counts of the rotation fix's candidates (:func:`.miho.choose_rotation`, the same
    decisions): for candidate linear parts ``rows`` ``(C, 2, 2)`` (entries 0 or +-1, one
    nonzero per row), the pairs whose midpoint distance ``|dx1 + R dx2| / 2`` lies in
    ``[lo, hi]`` (``(P,)`` each; ``dx1``, ``dx2`` ``(2, P)`` pair differences in each image),
    and how many of them differ from candidate 0's. Returns ``(scores, differ)``, ``(C,)``
    int64 each."""
    return _compiled()["_rotation_counts"](dx1, dx2, lo, hi, rows)


def greedy_cover(masks: np.ndarray, covered: np.ndarray, z: int) -> np.ndarray:
    """The top-z buffer's choice (``ransac._greedy_buffer``, the same): up to ``z`` rows of
    the candidates' inlier ``masks`` ``(C, n)`` bool, each the one (first of equals) with the
    most inliers not ``covered`` ``(n,)`` bool by the best model and the rows chosen before
    it, while that gain is positive. Returns their ``(<= z,)`` int64 row indices in order."""
    return _compiled()["_greedy_cover"](masks, covered, int(z))


class NearestGrid:
    """Exact ``q`` nearest neighbours of points ``feats`` ``(N, dims)`` float64 among
    themselves (Euclidean, the squared distance summed over dims in order, as scipy's k-d
    tree sums it), by a compiled search of a grid over the first two coordinates (about
    ``PER_CELL`` points a cell), rings of cells outwards until no point outside can come
    closer. Ties (equal distances) by index."""

    PER_CELL = 4
    MAX_CELLS = 1024

    def __init__(self, feats: np.ndarray) -> None:
        self.feats = np.ascontiguousarray(feats, dtype=np.float64)
        xy = self.feats[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        span = np.maximum(hi - lo, 1e-9)
        # at most MAX_CELLS cells a side: every point lies in the cell of its coordinates
        self.cell = float(max(np.sqrt(span[0] * span[1] * self.PER_CELL / len(xy)),
                              span.max() / self.MAX_CELLS, 1e-9))
        self.nx, self.ny = (int(v) for v in span // self.cell + 1)
        self.x0, self.y0 = float(lo[0]), float(lo[1])
        gx = np.clip(((xy[:, 0] - self.x0) / self.cell).astype(np.int64), 0, self.nx - 1)
        gy = np.clip(((xy[:, 1] - self.y0) / self.cell).astype(np.int64), 0, self.ny - 1)
        cell_of = gy * self.nx + gx
        self.members = np.argsort(cell_of, kind="stable")
        self.start = np.searchsorted(cell_of[self.members], np.arange(self.nx * self.ny + 1))

    def query(self, todo: np.ndarray, q: int) -> np.ndarray:
        """``(len(todo), q)`` int64: the ``q`` nearest points of each point ``todo``
        (indices), nearest first (the point itself, or a copy of it, first)."""
        return _compiled()["_nearest"](self.feats, np.asarray(todo, np.int64), int(q), self.x0,
                                       self.y0, self.cell, self.nx, self.ny, self.start,
                                       self.members)
