"""Local affine rectification: a patch homography pair per match from a least-squares affine fit to
its ``k`` nearest matches of the cluster (the filter's planes, fitted at a tolerance of several
pixels, can bias the NCC peak); matches with too few neighbours keep the filter's pair."""

from __future__ import annotations

import numpy as np

from . import kernel

#: re-weighted fits before the last one.
_ITERATIONS = 3
#: fewest neighbours (the match included) an affine fit needs; 3 determine it exactly.
MIN_NEIGHBOURS = 6


def local_affine_pairs(x1: np.ndarray, x2: np.ndarray, labels: np.ndarray, homs: np.ndarray, *,
                       k: int, max_residual_px: float, fit: np.ndarray | None = None,
                       rows: np.ndarray | None = None) -> np.ndarray:
    """Per-match patch homography pairs ``(I, A^-1)`` ``(M, 2, 3, 3)`` from local affine fits.

    ``labels`` ``(M,)`` cluster (-1: keeps identity); ``homs`` the filter's pairs where no fit is
    possible; ``fit`` the matches wanted (others keep the filter's pair); ``rows`` returns only
    those rows. A match's pair does not depend on which others are fitted."""
    m = x1.shape[0]
    labels = np.asarray(labels, np.int64)
    ok = labels >= 0
    want = ok if fit is None else ok & np.asarray(fit, bool)
    good, H_inv = kernel.fit_clusters(
        x1, x2, labels, want, k=k, max_residual_px=max_residual_px, iterations=_ITERATIONS,
        min_neighbours=MIN_NEIGHBOURS)
    sel = np.flatnonzero(good)
    H_inv = H_inv[sel]
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
