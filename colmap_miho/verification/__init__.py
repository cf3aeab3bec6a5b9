"""Pair verification: the image pairs that the rest of the pair graph contradicts (repeated
facades, symmetric buildings).

Modules:

- ``config``: :class:`PairCheckConfig` (thresholds, remove or flag).
- ``pair_graph``: :func:`check_pairs`, the triangles of the pair graph and the verdicts.
"""

from .config import PairCheckConfig
from .pair_graph import PairCheckResult, PairVerdict, check_pairs

__all__ = ["PairCheckConfig", "PairCheckResult", "PairVerdict", "check_pairs"]
