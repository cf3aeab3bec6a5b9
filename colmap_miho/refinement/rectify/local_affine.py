"""Local affine rectification: a patch homography pair per match from its nearest matches.

The filter's planes are fitted at a tolerance of several pixels, so the patch homography
pair of a cluster can be off by a few percent in scale or shear at a given keypoint; over a
21x21 template that biases the NCC peak by a tenth of a pixel or more. Here each refinable
match gets its own affine map image 1 -> image 2, fitted by least squares to the ``k``
nearest matches (in image 1) of the same cluster, re-fitted without the neighbours that miss
it (by twice the median residual, then by ``max_residual_px``). Matches with too few neighbours keep the filter's
pair.

The fits run compiled (:mod:`.kernel`); their numpy reference is in the tests
(``tests/affine_reference.py``).
"""

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
