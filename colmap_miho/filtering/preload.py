"""The warm-up of the compiled filter kernels (the ``filter`` family of
:mod:`colmap_miho.kernel_cache`); it lives above the filter's API, not in :mod:`.compiled`."""

from __future__ import annotations

import numpy as np

from .api import filter_matches
from .compiled import miho, ransac, sampling, scoring

#: the handles of the filter's compiled kernels, one per kernel module.
HANDLES = (sampling.KERNELS, scoring.KERNELS, ransac.KERNELS, miho.KERNELS)


def warm() -> bool:
    """Load every compiled filter kernel now by filtering two small synthetic pairs; whether they
    loaded. Never raises."""

    def example() -> None:
        rng = np.random.default_rng(0)
        x1 = rng.uniform(0, 500, (300, 2))
        filter_matches(x1, x1 + rng.normal(0, 0.5, x1.shape), seed=0)
        filter_matches(x1, rng.uniform(0, 500, (300, 2)), seed=0)

    # the example reaches every module's kernels: run it once (through one handle), check them all
    return sampling.KERNELS.warm(example) and all(h.loaded for h in HANDLES)
