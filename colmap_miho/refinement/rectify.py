"""Local affine rectification: a patch homography pair per match from its nearest matches.

The filter's planes are fitted at a tolerance of several pixels, so the patch homography
pair of a cluster can be off by a few percent in scale or shear at a given keypoint; over a
21x21 template that biases the NCC peak by a tenth of a pixel or more. Here each refinable
match gets its own affine map image 1 -> image 2, fitted by least squares to the ``k``
nearest matches (in image 1) of the same cluster, re-fitted without the neighbours that miss
it (by twice the median residual, then by ``max_residual_px``). Matches with too few neighbours keep the filter's
pair.

The fits run compiled (:mod:`.affine_kernel`) where numba is installed; :func:`_fit_rows` is
the numpy reference (and the path without numba). Pure numpy/scipy otherwise.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import affine_kernel

#: re-weighted fits before the last one.
_ITERATIONS = 3
#: fewest neighbours (the match included) an affine fit needs; 3 determine it exactly.
MIN_NEIGHBOURS = 6


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


def local_affine_pairs(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, homs: np.ndarray, *,
                       k: int, max_residual_px: float, fit: np.ndarray | None = None,
                       compiled: bool | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """Per-match patch homography pairs ``(I, A^-1)`` from local affine fits.

    Args:
        x1, x2: (M, 2) float64 matched pixel positions (integer = pixel centre).
        labels: (M,) int64 cluster of each match (-1: not refinable, keeps identity).
        homs: (K, 2, 3, 3) float64 the filter's pairs, used where a fit is not possible.
        k: neighbours per fit (the match included).
        max_residual_px: neighbours off the first fit by more than this are dropped.
        fit: optional (M,) bool, the matches whose pairs are wanted (their neighbours are
            drawn from all matches of their cluster all the same); the others keep the
            filter's pair unfitted. A match's pair does not depend on which others are
            fitted with it.
        compiled: fit with :mod:`.affine_kernel` (True) or numpy (False); None: compiled
            where numba is installed. The two differ at float rounding, and where several
            matches tie for a fit's last neighbour (the compiled fits take the lowest rows,
            numpy's k-d tree any of them).
        rows: optional (R,) int64 distinct rows: return only theirs (the ``fit`` matches must
            be among them).
    Returns:
        (M, 2, 3, 3) float64 pairs (A, B) with ``A x1 ~ B x2`` near each match (or (R, 2,
        3, 3), those of ``rows``).
    """
    m = x1.shape[0]
    labels = np.asarray(labels, np.int64)
    ok = labels >= 0
    want = ok if fit is None else ok & np.asarray(fit, bool)
    if compiled is None:
        compiled = affine_kernel.available()
    if compiled:
        good, H_inv = affine_kernel.fit_clusters(
            x1, x2, labels, want, k=k, max_residual_px=max_residual_px, iterations=_ITERATIONS,
            min_neighbours=MIN_NEIGHBOURS)
        sel = np.flatnonzero(good)
        H_inv = H_inv[sel]
    else:
        sel, H_inv = _fit_numpy(x1, x2, labels, want, k, max_residual_px)
    pos = np.arange(m) if rows is None else np.asarray(rows, np.int64)
    lab = labels[pos]
    out = np.tile(np.eye(3), (pos.size, 2, 1, 1))
    out[lab >= 0] = homs[lab[lab >= 0]]
    if rows is not None:
        at = np.full(m, -1, np.int64)
        at[pos] = np.arange(pos.size)
        sel = at[sel]
        if (sel < 0).any():
            raise ValueError("local_affine_pairs: the fitted matches must be among rows")
    out[sel, 0] = np.eye(3)
    out[sel, 1] = H_inv
    return out


def _fit_numpy(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, want: np.ndarray, k: int,
               max_residual_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The numpy path of :func:`local_affine_pairs`: (well-fitted rows (n,) int64, their
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
        good, H = _fit_rows(x1, x2, rows, nb, max_residual_px)
        sel.append(rows[good])
        inv.append(np.linalg.inv(H[good]))
    return np.concatenate(sel), np.concatenate(inv)


def _fit_rows(x1: np.ndarray, x2: np.ndarray, rows: np.ndarray, nb: np.ndarray,
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
