"""Compiled (numba) kernel of :mod:`..ransac`: the choice of a run's top-z buffer
(:func:`greedy_cover`, the same as ``ransac._greedy_buffer``). The batch scoring and the refit
it runs compiled are in :mod:`.scoring`, beside the helpers they share."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit


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
    j = jit()
    return {f.__name__: j(f) for f in (_greedy_cover,)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def greedy_cover(masks: np.ndarray, covered: np.ndarray, z: int) -> np.ndarray:
    """The top-z buffer's choice (``ransac._greedy_buffer``, the same): up to ``z`` rows of
    the candidates' inlier ``masks`` ``(C, n)`` bool, each the one (first of equals) with the
    most inliers not ``covered`` ``(n,)`` bool by the best model and the rows chosen before
    it, while that gain is positive. Returns their ``(<= z,)`` int64 row indices in order."""
    return KERNELS()["_greedy_cover"](masks, covered, int(z))
