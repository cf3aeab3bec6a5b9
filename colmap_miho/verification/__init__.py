"""Verification against the rest of the scene: the pair check (pairs the pair graph contradicts,
:mod:`.pair_graph`) and the match check (every match against a global estimate,
:mod:`.match_check`)."""

from .config import MatchCheckConfig, PairCheckConfig
from .match_check import MatchCheckDecision, MatchCheckResult, check_matches, judge_in_rounds
from .pair_graph import PairCheckResult, PairVerdict, check_pairs

__all__ = ["MatchCheckConfig", "MatchCheckDecision", "MatchCheckResult", "PairCheckConfig", "PairCheckResult",
           "PairVerdict", "check_matches", "check_pairs", "judge_in_rounds"]
