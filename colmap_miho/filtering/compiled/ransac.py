"""Compiled (numba) kernel of :mod:`..ransac`: the choice of a run's top-z buffer (batch scoring and
refit are in :mod:`.scoring`, beside their helpers)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit


def _greedy_cover(masks, covered, z):
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
    j = jit()
    return {f.__name__: j(f) for f in (_greedy_cover,)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def greedy_cover(masks: np.ndarray, covered: np.ndarray, z: int) -> np.ndarray:
    """Up to ``z`` rows of ``masks`` ``(C, n)``, each adding the most inliers not yet ``covered``
    while the gain is positive; their int64 indices in order."""
    return KERNELS()["_greedy_cover"](masks, covered, int(z))
