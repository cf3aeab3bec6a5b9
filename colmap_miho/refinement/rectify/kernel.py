"""Compiled (numba) local affine fits for :mod:`.local_affine`: each wanted match's ``k`` nearest
matches of its cluster on a grid, and a weighted least-squares affine map refitted without those
that miss it, one loop per match (the numpy reference pays a LAPACK call per 3x3 problem)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ...compiled import Kernels, jit, jit_helpers

#: conditioning bound of the normal matrix: smallest eigenvalue over largest (as the
#: numpy path's).
MIN_EIGEN_RATIO = 1e-8
#: smallest determinant of the linear part of a well-fitted map (as the numpy path's).
MIN_DET = 1e-3


def _extreme_eigenvalues(S) -> tuple[float, float]:
    """(smallest, largest) eigenvalue of the symmetric (3, 3) ``S`` (closed form)."""
    a, b, c = S[0, 0], S[1, 1], S[2, 2]
    d, e, f = S[0, 1], S[0, 2], S[1, 2]
    p1 = d * d + e * e + f * f
    if p1 == 0.0:
        return min(a, min(b, c)), max(a, max(b, c))
    q = (a + b + c) / 3.0
    aq, bq, cq = a - q, b - q, c - q
    p = math.sqrt((aq * aq + bq * bq + cq * cq + 2.0 * p1) / 6.0)
    aq, bq, cq, d, e, f = aq / p, bq / p, cq / p, d / p, e / p, f / p
    half_det = 0.5 * (aq * (bq * cq - f * f) - d * (d * cq - f * e) + e * (d * f - bq * e))
    phi = math.acos(min(max(half_det, -1.0), 1.0)) / 3.0
    return q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0), q + 2.0 * p * math.cos(phi)


def _solve3(M, B) -> None:
    """Solve ``M X = B`` in place by Gaussian elimination with partial pivoting (``B`` becomes ``X``)."""
    for j in range(3):
        p = j
        for i in range(j + 1, 3):
            if abs(M[i, j]) > abs(M[p, j]):
                p = i
        if p != j:
            for c in range(3):
                M[j, c], M[p, c] = M[p, c], M[j, c]
            for c in range(2):
                B[j, c], B[p, c] = B[p, c], B[j, c]
        for i in range(j + 1, 3):
            M[i, j] = M[i, j] / M[j, j]
            for c in range(j + 1, 3):
                M[i, c] = M[i, c] - M[i, j] * M[j, c]
    for c in range(2):
        for i in range(3):
            for q in range(i):
                B[i, c] = B[i, c] - M[i, q] * B[q, c]
        for i in range(2, -1, -1):
            for q in range(i + 1, 3):
                B[i, c] = B[i, c] - M[i, q] * B[q, c]
            B[i, c] = B[i, c] / M[i, i]


def _fit(x1n, x2n, w, A, M, B) -> bool:
    """Weighted least squares ``x2n ~ A [x1n; 1]`` into ``A`` ``(2, 3)``; whether the normal matrix
    is well-conditioned (else the identity, as numpy's path)."""
    k = x1n.shape[0]
    for a in range(3):
        for b in range(3):
            s = 0.0
            for j in range(k):
                xa = x1n[j, a] if a < 2 else 1.0
                xb = x1n[j, b] if b < 2 else 1.0
                s += (xa * w[j]) * xb
            M[a, b] = s
        for b in range(2):
            s = 0.0
            for j in range(k):
                xa = x1n[j, a] if a < 2 else 1.0
                s += (xa * w[j]) * x2n[j, b]
            B[a, b] = s
    lo, hi = _extreme_eigenvalues(M)
    ok = math.isfinite(lo) and math.isfinite(hi) and lo > MIN_EIGEN_RATIO * hi
    if not ok:
        for a in range(3):
            for b in range(3):
                M[a, b] = 1.0 if a == b else 0.0
    _solve3(M, B)
    for c in range(2):
        for a in range(3):
            A[c, a] = B[a, c]
    return ok


def _fit_matches(x1, x2, rows, nb, max_residual_px, iterations, min_neighbours, good, H, H_inv):
    """Per match ``rows[i]`` with neighbours ``nb[i]``: ``good[i]``, ``H[i]`` and its inverse."""
    n, k = nb.shape
    x1n, x2n = np.empty((k, 2)), np.empty((k, 2))
    w, r, srt = np.empty(k), np.empty(k), np.empty(k)
    A, M, B = np.empty((2, 3)), np.empty((3, 3)), np.empty((3, 2))
    for i in range(n):
        c = rows[i]
        for j in range(k):
            for d in range(2):
                x1n[j, d] = x1[nb[i, j], d] - x1[c, d]
                x2n[j, d] = x2[nb[i, j], d] - x2[c, d]
            w[j] = 1.0
        ok = False
        for it in range(iterations):
            ok = _fit(x1n, x2n, w, A, M, B)
            for j in range(k):
                dx = (x1n[j, 0] * A[0, 0] + x1n[j, 1] * A[0, 1]) + A[0, 2] - x2n[j, 0]
                dy = (x1n[j, 0] * A[1, 0] + x1n[j, 1] * A[1, 1]) + A[1, 2] - x2n[j, 1]
                r[j] = math.sqrt(dx * dx + dy * dy)
            bound = max_residual_px
            if it < iterations - 1:  # the median residual first, the absolute bound last
                srt[:] = r
                srt.sort()
                h = k // 2
                median = srt[h] if k % 2 else 0.5 * (srt[h - 1] + srt[h])
                bound = max(max_residual_px, 2.0 * median)
            for j in range(k):
                w[j] = 1.0 if r[j] <= bound else 0.0
        ok = _fit(x1n, x2n, w, A, M, B) and ok
        kept = 0.0
        for j in range(k):
            kept += w[j]
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        good[i] = ok and kept >= min_neighbours and det > MIN_DET
        # x2 = c2 + L (x1 - c1) + t
        tx = x2[c, 0] + A[0, 2] - (A[0, 0] * x1[c, 0] + A[0, 1] * x1[c, 1])
        ty = x2[c, 1] + A[1, 2] - (A[1, 0] * x1[c, 0] + A[1, 1] * x1[c, 1])
        H[i, 0, 0], H[i, 0, 1], H[i, 0, 2] = A[0, 0], A[0, 1], tx
        H[i, 1, 0], H[i, 1, 1], H[i, 1, 2] = A[1, 0], A[1, 1], ty
        H[i, 2, 0], H[i, 2, 1], H[i, 2, 2] = 0.0, 0.0, 1.0
        if good[i]:
            i00, i01, i10, i11 = A[1, 1] / det, -A[0, 1] / det, -A[1, 0] / det, A[0, 0] / det
            H_inv[i, 0, 0], H_inv[i, 0, 1], H_inv[i, 0, 2] = i00, i01, -(i00 * tx + i01 * ty)
            H_inv[i, 1, 0], H_inv[i, 1, 1], H_inv[i, 1, 2] = i10, i11, -(i10 * tx + i11 * ty)
        else:
            for a in range(2):
                for b in range(3):
                    H_inv[i, a, b] = 1.0 if a == b else 0.0
        H_inv[i, 2, 0], H_inv[i, 2, 1], H_inv[i, 2, 2] = 0.0, 0.0, 1.0


#: points per cell of the grid that :func:`_fit_clusters` searches a cluster's neighbours in.
_POINTS_PER_CELL = 2.0


def _insert(d: float, j: int, k: int, nb, dist) -> None:
    """Put candidate ``j`` at squared distance ``d`` among the ``k`` nearest so far, if it is one."""
    if d < dist[k - 1] or (d == dist[k - 1] and j < nb[k - 1]):
        i = k - 1
        while i > 0 and (d < dist[i - 1] or (d == dist[i - 1] and j < nb[i - 1])):
            dist[i], nb[i] = dist[i - 1], nb[i - 1]
            i -= 1
        dist[i], nb[i] = d, j


def _nearest(xs, ys, cell_x, cell_y, start, order, gx, gy, side, p, k, nb, dist) -> None:
    """The ``k`` nearest points to point ``p`` of a cluster on its grid (nearest first, ties to the
    lower index), searched ring by ring until no farther cell can hold a nearer point."""
    for j in range(k):
        dist[j], nb[j] = math.inf, -1
    qx, qy, cx, cy = xs[p], ys[p], cell_x[p], cell_y[p]
    r = 0
    while True:
        for iy in range(max(cy - r, 0), min(cy + r, gy - 1) + 1):
            edge = iy == cy - r or iy == cy + r
            for ix in range(max(cx - r, 0), min(cx + r, gx - 1) + 1):
                if not edge and ix != cx - r and ix != cx + r:
                    continue  # inside the ring: searched already
                c = iy * gx + ix
                for t in range(start[c], start[c + 1]):
                    j = order[t]
                    dx, dy = xs[j] - qx, ys[j] - qy
                    _insert(dx * dx + dy * dy, j, k, nb, dist)
        reach = r * side * (1.0 - 1e-9)  # a margin for the rounding of the cells' bounds
        if (reach * reach > dist[k - 1]) or (r >= gx and r >= gy):
            break
        r += 1


def _fit_clusters(x1, x2, members, bounds, want, k, max_residual_px, iterations, min_neighbours,
                  good, H_inv) -> None:
    """Per cluster, the neighbours and fits of its ``want`` rows, into ``good`` and ``H_inv``."""
    for c in range(bounds.size - 1):
        cl = members[bounds[c]:bounds[c + 1]]
        n = cl.size
        kk = min(k, n)
        if kk < min_neighbours:
            continue
        xs, ys = np.empty(n), np.empty(n)
        for i in range(n):
            xs[i], ys[i] = x1[cl[i], 0], x1[cl[i], 1]
        x0, y0 = xs.min(), ys.min()
        w, h = max(xs.max() - x0, 1e-9), max(ys.max() - y0, 1e-9)
        side = max(math.sqrt(w * h * _POINTS_PER_CELL / n), 1e-9)
        gx = min(int(w / side) + 1, n + 1)
        gy = min(int(h / side) + 1, n + 1)
        side = max(w / gx, h / gy) * (1.0 + 1e-12)
        cell_x, cell_y = np.empty(n, np.int64), np.empty(n, np.int64)
        start = np.zeros(gx * gy + 1, np.int64)
        for i in range(n):
            cell_x[i] = min(int((xs[i] - x0) / side), gx - 1)
            cell_y[i] = min(int((ys[i] - y0) / side), gy - 1)
            start[cell_y[i] * gx + cell_x[i] + 1] += 1
        for i in range(gx * gy):
            start[i + 1] += start[i]
        order, fill = np.empty(n, np.int64), start[:-1].copy()
        for i in range(n):  # ascending within a cell
            cc = cell_y[i] * gx + cell_x[i]
            order[fill[cc]] = i
            fill[cc] += 1
        at = np.flatnonzero(want[cl])
        rows = cl[at]
        nb = np.empty((at.size, kk), np.int64)
        dist = np.empty(kk)
        for i in range(at.size):
            _nearest(xs, ys, cell_x, cell_y, start, order, gx, gy, side, at[i], kk, nb[i], dist)
            for j in range(kk):
                nb[i, j] = cl[nb[i, j]]
        g = np.zeros(at.size, np.bool_)
        H, Hi = np.empty((at.size, 3, 3)), np.empty((at.size, 3, 3))
        _fit_matches(x1, x2, rows, nb, max_residual_px, iterations, float(min_neighbours), g, H, Hi)
        for i in range(at.size):
            good[rows[i]] = g[i]
            H_inv[rows[i]] = Hi[i]


def _jit_all() -> tuple[Any, Any]:
    jit_helpers(globals(), (_extreme_eigenvalues, _solve3, _fit, _fit_matches, _insert, _nearest))
    return globals()["_fit_matches"], jit()(_fit_clusters)


#: the jitted kernels (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def fit_rows(x1: np.ndarray, x2: np.ndarray, rows: np.ndarray, nb: np.ndarray, *,
             max_residual_px: float, iterations: int, min_neighbours: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust local affine maps image 1 -> image 2 at the matches ``rows`` with neighbours ``nb``
    ``(n, k)``, k >= 3. Returns ``(good (n,), H, H_inv (n, 3, 3))``, identity where not good."""
    rows = np.ascontiguousarray(rows, np.int64)
    nb = np.ascontiguousarray(nb, np.int64)
    n = rows.size
    good = np.zeros(n, np.bool_)
    H, H_inv = np.empty((n, 3, 3)), np.empty((n, 3, 3))
    if n:
        KERNELS()[0](np.ascontiguousarray(x1, np.float64), np.ascontiguousarray(x2, np.float64),
                     rows, nb, float(max_residual_px), int(iterations), float(min_neighbours),
                     good, H, H_inv)
    return good, H, H_inv


def fit_clusters(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, want: np.ndarray, *, k: int,
                 max_residual_px: float, iterations: int, min_neighbours: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Local affine maps of the ``want`` matches, each fitted to its nearest matches in image 1
    within its cluster (``labels``; -1 never fitted; clusters under ``min_neighbours`` not fitted).

    Returns ``(good (M,), H_inv (M, 3, 3))`` with ``x1 ~ H_inv x2`` where good. ValueError for a
    non-finite position in a cluster to fit."""
    x1 = np.ascontiguousarray(x1, np.float64)
    labels = np.asarray(labels, np.int64)
    m = labels.size
    good = np.zeros(m, np.bool_)
    H_inv = np.empty((m, 3, 3))
    used = np.zeros(int(labels.max(initial=-1)) + 2, np.bool_)  # last: label -1
    want = np.asarray(want, bool) & (labels >= 0)
    used[labels[want]] = True
    used[-1] = False
    cand = np.flatnonzero(used[labels])
    if not cand.size:
        return good, H_inv
    if not np.isfinite(x1[cand]).all():  # the grid needs finite positions
        raise ValueError("fit_clusters: the positions in image 1 of the clusters to fit must be finite")
    members = cand[np.argsort(labels[cand], kind="stable")]  # by cluster, rows ascending
    lab = labels[members]
    bounds = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1], True])
    KERNELS()[1](x1, np.ascontiguousarray(x2, np.float64), members, bounds.astype(np.int64),
                 want, int(k), float(max_residual_px), int(iterations), int(min_neighbours),
                 good, H_inv)
    return good, H_inv


def warm() -> bool:
    """Load (or compile) the kernels now on a small cluster; whether they loaded. Never raises."""

    def example() -> None:
        t = np.arange(8, dtype=np.float64)
        x1 = np.c_[np.repeat(t, 8), np.tile(t, 8)] * 5.0
        fit_clusters(x1, 1.1 * x1 + 2.0, np.zeros(64, np.int64), np.ones(64, bool), k=12,
                     max_residual_px=2.0, iterations=3, min_neighbours=6)

    return KERNELS.warm(example)
