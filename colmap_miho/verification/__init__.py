"""Verification against the rest of the scene: the match check (every match judged against a
global estimate of the cameras).

Modules:

- ``config``: :class:`MatchCheckConfig` (thresholds, remove or flag).
- ``match_check``: :func:`judge_in_rounds`, the match check (estimates from an estimator
  passed in, judgement by :func:`check_matches`, re-placement of the images not trusted); its
  result is :class:`MatchCheckDecision` (one round's judgement: ``Judgement``).
- ``estimator``: what the check asks of a global estimate and of its estimator (protocols).
- ``hinge``: finding and resolving a hinged estimate (:func:`~.hinge.resolve_hinge`).
- ``restore``: the filter's removals given back where the estimate proves them.
"""

from .config import MatchCheckConfig
from .match_check import MatchCheckDecision, check_matches, judge_in_rounds

__all__ = ["MatchCheckConfig", "MatchCheckDecision", "check_matches", "judge_in_rounds"]
