"""Compiled (numba) kernels of :mod:`..ransac`: a batch's whole full scoring and its
search's choices (:func:`score_batch`), the least-squares refit of a run's best model
(:func:`refit`), the choice of a run's top-z buffer (:func:`greedy_cover`), each in one call.

The refit adds its products in a fixed order where numpy's matmul (BLAS) may fuse or reorder
them, so its homography can differ in the last bits."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit, jit_helpers
from . import homography
from .homography import adjugate, hypothesis_rows, mask_row, normalised, sign_of, sv_ok_one


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
            if ub[k] > 0 and sv_ok_one(sample, k, src_all, dst_all, min_sv, p4, q4, s4, d4, A):
                hypothesis_rows(H, sign, Hinv, sign_inv, k, True, hk)
                mask_row(hk, pts, t2, s2, masks[p])
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
    ``T[3, 3]`` the similarity (:func:`..homography.normalise_points`)."""
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
        adjugate(e, adj)
        Ht = np.empty((3, 3))
        for r in range(3):
            for c in range(3):
                Ht[r, c] = adj[3 * r] * Hn[0, c] + adj[3 * r + 1] * Hn[1, c] + adj[3 * r + 2] * Hn[2, c]
        for r in range(3):
            for c in range(3):
                e[3 * r + c] = Ht[r, 0] * T1[0, c] + Ht[r, 1] * T1[1, c] + Ht[r, 2] * T1[2, c]
        if not normalised(e):
            return False, H, Hinv, sign, sign_inv
        adjugate(e, adj)
        for direction in range(2):
            m = e if direction == 0 else adj
            pts = src_all if direction == 0 else dst_all
            first = 0.0
            for i in range(4):
                j = sample[i]
                w = m[6] * pts[j, h, 0] + m[7] * pts[j, h, 1] + m[8]
                sg = sign_of(w)
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


def _jit_all() -> dict[str, Any]:
    """Jit every kernel and the helpers they call (numpy's error model: a division by zero
    gives inf / nan, and those entries fail the sign test)."""
    globals().update(homography.KERNELS())  # the shared helpers, jitted once
    jit_helpers(globals(), (_normalising,))
    j = jit()
    return {f.__name__: j(f) for f in (_refit, _greedy_cover, _score_batch)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def score_batch(ub: np.ndarray, count: int, have_best: bool, n_req: int, z: int,
                H: np.ndarray, Hinv: np.ndarray, sign: np.ndarray, sign_inv: np.ndarray,
                sample: np.ndarray, src_all: np.ndarray, dst_all: np.ndarray, min_sv: float,
                pts: np.ndarray, t2: float, s2: float):
    """The full scoring of one batch of hypotheses in one call (``ransac._score_batch``'s
    loop and its search's choices, the same decisions): in descending order of their
    one-way bounds ``ub`` ``(K,)`` (stable), groups of 4 are scored (bound > 0,
    :func:`.scoring.singular_value_ok`, then :func:`.scoring.inlier_masks`) while a bound can beat the best count
    (``count`` at the start) or a group holds one of the batch's two strongest with at
    least ``n_req`` possible inliers (at most ``z``); within a group the hypotheses are
    taken by count, descending: one above the best becomes the best (the best it replaces,
    if ``have_best``, becomes a candidate), another with inliers a candidate.

    Returns ``(order, masks, events, best, count, scored)``: the order ``(K,)`` (position
    -> hypothesis row), the masks ``(R, n)`` by position (rows of scored positions only),
    the candidates ``(E,)`` in the order they arose (positions; -1: the best from before the
    batch), the new best's position (-1: unchanged), the best count and the number of
    hypotheses scored. ``H``, ``Hinv``, signs and ``sample`` ``(K, ...)``: the hypotheses;
    ``src_all``, ``dst_all``, ``min_sv`` as :func:`.scoring.singular_value_ok`; ``pts``, ``t2``,
    ``s2`` as :func:`.scoring.inlier_masks`.
    """
    return KERNELS()["_score_batch"](ub, int(count), bool(have_best), int(n_req), int(z),
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
    return KERNELS()["_refit"](idx, src_all, dst_all, sample)


def greedy_cover(masks: np.ndarray, covered: np.ndarray, z: int) -> np.ndarray:
    """The top-z buffer's choice (``ransac._greedy_buffer``, the same): up to ``z`` rows of
    the candidates' inlier ``masks`` ``(C, n)`` bool, each the one (first of equals) with the
    most inliers not ``covered`` ``(n,)`` bool by the best model and the rows chosen before
    it, while that gain is positive. Returns their ``(<= z,)`` int64 row indices in order."""
    return KERNELS()["_greedy_cover"](masks, covered, int(z))
