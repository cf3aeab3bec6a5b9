"""Pair verification: the image pairs that the rest of the pair graph contradicts (repeated
facades, symmetric buildings).

Modules:

- ``config``: :class:`PairCheckConfig` (thresholds, remove or flag).
- ``pair_graph``: :func:`check_pairs`, the triangles of the pair graph and the verdicts.
- ``match_check``: :func:`check_matches`, every match judged against a global estimate of the
  cameras (:class:`MatchCheckConfig`).
"""

from .config import MatchCheckConfig, PairCheckConfig
from .match_check import MatchCheckResult, check_matches
from .pair_graph import PairCheckResult, PairVerdict, check_pairs

__all__ = ["MatchCheckConfig", "MatchCheckResult", "PairCheckConfig", "PairCheckResult", "PairVerdict",
           "check_matches", "check_pairs"]
