"""The run's seeds: one root seed (``--seed``, ``seed=``; 0 by default) and every stage's own,
derived from it here and nowhere else, so that a run is repeated exactly from its root alone.

- filter: pair (i, j) draws from :func:`pair_seed` (root, i, j), whatever the worker or chunk;
- match check: the root itself (the track sample, the global mapper, each pair's RANSAC);
- mapping: the root, plus k for the k-th repeat of ``run`` / ``compare --repeats``;
- the two-view protocols of ``report`` / ``compare``: the root.
"""

from __future__ import annotations

import numpy as np


def pair_seed(root: int, image_id1: int, image_id2: int) -> int:
    """The filter's seed of one pair, independent of worker count and order."""
    return int(np.random.SeedSequence([int(root), int(image_id1), int(image_id2)]).generate_state(1)[0])


def match_check_seed(root: int) -> int:
    """The match check's seed."""
    return int(root)


def mapping_seed(root: int, repeat: int = 0) -> int:
    """The mapper's seed of the ``repeat``-th mapping run (0: the first)."""
    return int(root) + int(repeat)
