"""Verification against the rest of the scene: the pair check (image pairs that the rest of the
pair graph contradicts: repeated facades, symmetric buildings) and the match check (every match
judged against a global estimate of the cameras).

Modules:

- ``config``: :class:`PairCheckConfig` and :class:`MatchCheckConfig` (thresholds, remove or flag).
- ``pair_graph``: :func:`check_pairs`, the triangles of the pair graph and the verdicts.
- ``match_check``: :func:`judge_in_rounds`, the match check (estimates from an estimator
  passed in, judgement by :func:`check_matches`, re-placement of the images not trusted).
"""

from .config import MatchCheckConfig, PairCheckConfig
from .match_check import MatchCheckDecision, MatchCheckResult, check_matches, judge_in_rounds
from .pair_graph import PairCheckResult, PairVerdict, check_pairs

__all__ = ["MatchCheckConfig", "MatchCheckDecision", "MatchCheckResult", "PairCheckConfig", "PairCheckResult",
           "PairVerdict", "check_matches", "check_pairs", "judge_in_rounds"]
