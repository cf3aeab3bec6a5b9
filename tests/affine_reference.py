"""The numpy reference of the local affine fits (:mod:`colmap_miho.refinement.rectify.local_affine`, run
compiled by :mod:`colmap_miho.refinement.rectify.kernel`): a k-d tree per cluster, then batched
weighted least squares. The two differ at float rounding, and where several matches tie for a
fit's last neighbour (the compiled fits take the lowest rows, the k-d tree any of them)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from colmap_miho.refinement.rectify.local_affine import _ITERATIONS, MIN_NEIGHBOURS


def local_affine_pairs_numpy(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, homs: np.ndarray, *,
                             k: int, max_residual_px: float) -> np.ndarray:
    """:func:`colmap_miho.refinement.rectify.local_affine.local_affine_pairs` (every match, all rows) by
    numpy: (M, 2, 3, 3) float64 pairs."""
    labels = np.asarray(labels, np.int64)
    ok = labels >= 0
    sel, H_inv = _fit_numpy(x1, x2, labels, ok, k, max_residual_px)
    out = np.tile(np.eye(3), (x1.shape[0], 2, 1, 1))
    out[ok] = homs[labels[ok]]
    out[sel, 0] = np.eye(3)
    out[sel, 1] = H_inv
    return out


def _fit(x1n: np.ndarray, x2n: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted batched least squares x2 ~ A [x1; 1]: (n, k, 2) each, weights (n, k).
    Returns (A (n, 2, 3), well-conditioned (n,) bool)."""
    X = np.concatenate([x1n, np.ones(x1n.shape[:2] + (1,))], axis=2)  # (n, k, 3)
    Xw = X * w[..., None]
    XwT = Xw.transpose(0, 2, 1)
    XtX = XwT @ X
    XtY = XwT @ x2n
    ev = np.linalg.eigvalsh(XtX)  # symmetric: condition number from its eigenvalues
    ok = np.isfinite(ev).all(axis=1) & (ev[:, 0] > 1e-8 * ev[:, 2])
    XtX[~ok] = np.eye(3)
    A = np.linalg.solve(XtX, XtY)  # (n, 3, 2)
    return A.transpose(0, 2, 1), ok


def _fit_numpy(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, want: np.ndarray, k: int,
               max_residual_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The numpy fits of :func:`local_affine_pairs_numpy`: (well-fitted rows (n,) int64, their
    inverse maps (n, 3, 3) float64)."""
    by_size: dict[int, tuple[list, list]] = {}  # neighbours per fit -> (rows, neighbours)
    for lab in np.unique(labels[want]):
        rows = np.flatnonzero(labels == lab)
        kk = min(k, rows.size)
        if kk < MIN_NEIGHBOURS:
            continue
        q = np.flatnonzero(want[rows])
        _, nn = cKDTree(x1[rows]).query(x1[rows[q]], k=kk)
        got = by_size.setdefault(kk, ([], []))
        got[0].append(rows[q])
        got[1].append(rows[nn])
    sel, inv = [np.zeros(0, np.int64)], [np.zeros((0, 3, 3))]
    for rows_l, nb_l in by_size.values():
        # clusters with the same neighbour count in one batch: every step below is per
        # match (batched matmul, eigvalsh, solve, median act on each row alone)
        rows, nb = np.concatenate(rows_l), np.concatenate(nb_l)  # (n,), (n, kk)
        good, H = fit_rows(x1, x2, rows, nb, max_residual_px)
        sel.append(rows[good])
        inv.append(np.linalg.inv(H[good]))
    return np.concatenate(sel), np.concatenate(inv)


def fit_rows(x1: np.ndarray, x2: np.ndarray, rows: np.ndarray, nb: np.ndarray,
              max_residual_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust local affine maps image 1 -> image 2 at the matches ``rows`` from their
    neighbours ``nb`` (n, kk): (well-fitted (n,) bool, H (n, 3, 3) float64)."""
    c1, c2 = x1[rows], x2[rows]
    x1n, x2n = x1[nb] - c1[:, None], x2[nb] - c2[:, None]  # centred on the match
    w = np.ones(nb.shape)
    for it in range(_ITERATIONS):
        A, good = _fit(x1n, x2n, w)
        pred = x1n @ A[:, :, :2].transpose(0, 2, 1) + A[:, None, :, 2]
        r = np.linalg.norm(pred - x2n, axis=2)
        # a gross outlier inflates every residual of the first fits: drop by the
        # median residual first, by the absolute bound last
        bound = max_residual_px if it == _ITERATIONS - 1 else np.maximum(
            max_residual_px, 2.0 * np.median(r, axis=1, keepdims=True))
        w = (r <= bound).astype(np.float64)
    A, good2 = _fit(x1n, x2n, w)
    good &= good2 & (w.sum(axis=1) >= MIN_NEIGHBOURS)
    # full affine image 1 -> image 2 around the match: x2 = c2 + L (x1 - c1) + t
    L, t = A[:, :, :2], A[:, :, 2]
    det = np.linalg.det(L)
    good &= det > 1e-3
    H = np.tile(np.eye(3), (rows.size, 1, 1))
    H[:, :2, :2] = L
    H[:, :2, 2] = c2 + t - np.einsum("nij,nj->ni", L, c1)
    return good, H
