"""The match check on a survey with a planted hinge (consistent wrong pairs between two halves,
:mod:`miho_bench.hinge_scene`), with pycolmap's global mapper as the estimate: the hinge is found
and no correct match is removed on it; a planted hypothesis that is wrong is rejected."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.pipeline.match_check_stage import MatchCheckStats
from colmap_miho.reporting.html_report import match_check_note
from colmap_miho.sfm.global_estimate import GlobalEstimator
from colmap_miho.verification import MatchCheckConfig, judge_in_rounds
from miho_bench.hinge_scene import make_hinged_survey
from miho_bench.variants import variant

pytestmark = pytest.mark.slow

#: The issue's bound: correct matches the check may remove.
MAX_CORRECT_REMOVED = 0.03
#: Wrong matches the check must remove once the hinge is resolved (they are whole wrong pairs).
MIN_WRONG_REMOVED = 0.9


def _judge(scene, **cfg):
    with ColmapDatabase(scene.database) as db:
        config = variant(MatchCheckConfig(mode="remove"), **cfg)  # look_for_hinges: a class constant
        d = judge_in_rounds(scene.matches, GlobalEstimator(src=db, config=config, num_threads=1), config)
        names = {im.image_id: im.name for im in db.images()}
    pairs = sorted(scene.matches)
    ok = np.concatenate([scene.correct[p] for p in pairs])
    failed = np.concatenate([d.failed.get(p, np.zeros(len(scene.matches[p]), bool)) for p in pairs])
    return d, float(failed[ok].mean()), float(failed[~ok].mean()), names


@pytest.mark.parametrize("wrong_per_right", [1.0, 2.0, 4.0])
def test_a_planted_hinge_is_found_and_removes_no_correct_match(tmp_path, wrong_per_right):
    scene = make_hinged_survey(tmp_path, wrong_per_right=wrong_per_right, seed=0)
    assert len(scene.wrong_pairs) >= wrong_per_right * len(scene.correct_cross) * 0.9 or len(scene.wrong_pairs) > 40
    plain, correct_plain, _, _ = _judge(scene, look_for_hinges=False)
    assert correct_plain > 0.1  # the mapper sides with the wrong pairs: the check without the hinge fails here
    d, correct, wrong, names = _judge(scene)
    assert d.used and d.hinges
    assert d.hinges[0].verdict == "mode" and d.hinges[0].action == "estimated again"
    assert correct <= MAX_CORRECT_REMOVED
    assert wrong >= MIN_WRONG_REMOVED
    stats = MatchCheckStats.of(d, MatchCheckConfig(mode="remove"), scene.matches, names).to_dict()
    h = stats["hinges"][0]
    assert h["verdict"] == "mode" and h["action"] == "estimated again" and h["mode_coverage"] > h["estimate_coverage"]
    assert "Hinge in round 1's estimate" in match_check_note(stats) and "made again" in match_check_note(stats)


def test_more_matches_on_the_wrong_pairs(tmp_path):
    """The planted wrong pairs hold more matches than the correct pairs across (a repeated
    element gives many): no count can side with the correct ones."""
    scene = make_hinged_survey(tmp_path, wrong_per_right=1.0, repeated_share=0.8, seed=0)
    wrong = np.median([len(scene.matches[p]) for p in scene.wrong_pairs])
    right = np.median([len(scene.matches[p]) for p in scene.correct_cross])
    assert wrong > right
    _, correct_plain, _, _ = _judge(scene, look_for_hinges=False)
    d, correct, wrong_removed, _ = _judge(scene)
    assert correct_plain > 0.1 and correct <= MAX_CORRECT_REMOVED and d.hinges


@pytest.mark.parametrize("turn_deg", [30.0, 60.0])
def test_a_planted_wrong_hypothesis_is_rejected(tmp_path, turn_deg):
    """Wrong pairs agreeing with one another on a group turned by 30-60 deg, a third as many as
    the correct ones: the estimate stays right, the wrong pairs form a mode, and the arbiter
    keeps the estimate; the verdicts are those of the check without the hinge search."""
    scene = make_hinged_survey(tmp_path, wrong_per_right=0.3, turn_deg=turn_deg, seed=1)
    plain, correct_plain, wrong_plain, _ = _judge(scene, look_for_hinges=False)
    assert correct_plain <= MAX_CORRECT_REMOVED  # the premise: the estimate is right
    d, correct, wrong, _ = _judge(scene)
    assert d.hinges, "the planted wrong pairs form a mode"
    assert all(h.verdict == "estimate" and h.action == "kept" and not h.unjudged for h in d.hinges)
    assert correct == correct_plain <= MAX_CORRECT_REMOVED and wrong == wrong_plain >= MIN_WRONG_REMOVED
    assert d.failed.keys() == plain.failed.keys()
    assert all(np.array_equal(d.failed[p], plain.failed[p]) for p in d.failed)


def test_without_wrong_pairs_no_hinge_is_found(tmp_path):
    scene = make_hinged_survey(tmp_path, wrong_per_right=0.0, seed=2)
    d, correct, _, _ = _judge(scene)
    assert d.used and not d.hinges and correct <= MAX_CORRECT_REMOVED
