"""Compiled (numba) kernel of :mod:`..miho`: the rotation fix's pair counts."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit


def _rotation_counts(dx1, dx2, lo, hi, rows):
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


def _jit_all() -> dict[str, Any]:
    j = jit()
    return {f.__name__: j(f) for f in (_rotation_counts,)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def rotation_counts(dx1: np.ndarray, dx2: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(scores, differ)`` ``(C,)``: for each candidate ``rows[c]`` the pairs whose midpoint
    distance ``|dx1 + R dx2| / 2`` lies in ``[lo, hi]``, and how many decide unlike candidate 0."""
    return KERNELS()["_rotation_counts"](dx1, dx2, lo, hi, rows)
