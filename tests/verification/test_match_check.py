"""Match check core: matches judged against a global estimate of the cameras (pure numpy, GT
scene with planted wrong matches that are consistent per pair, as repeated structure makes them)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.geometry import essential, relative_pose, symmetric_epipolar_distance
from colmap_miho.verification import MatchCheckConfig, check_matches, judge_in_rounds
from colmap_miho.verification.match_check import (
    LATER_ROUND_RINGS,
    cut_off_images,
    images_around,
    robust_scale,
    threshold_px,
    trusted_images,
)

FOCAL = 800.0
#: Pixels: noise of the correct matches' keypoints.
NOISE_PX = 0.5
#: A repeated structure's period (world units) along the facade: the wrong matches join a point
#: with the one nearest to it shifted by this.
PERIOD = np.array([0.0, 0.5, 0.0])
#: Correct matches the check may remove (the threshold's tail) and planted ones it may keep
#: (a planted match whose shift runs along its epipolar line is invisible to any epipolar test).
MAX_CORRECT_REMOVED = 0.03
MAX_PLANTED_KEPT = 0.1


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _scene(seed: int = 0, n_images: int = 8, n_points: int = 600, planted: float = 0.25):
    """Cameras on an arc around a box of points; every pair matches the points both see, plus
    ``planted`` as many wrong matches (point P in image i with the point nearest P + PERIOD in
    image j, consistent per pair). Returns poses, rays, focal, matches and the planted masks."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-2, -1, -0.5], [2, 1, 0.5], (n_points, 3))
    poses = {}
    for k in range(n_images):
        ang = -30 + 60 * k / (n_images - 1)
        R = _rot([0, 1, 0], ang)
        center = -R.T @ np.array([0.0, 0.0, 0.0]) + np.array([6 * np.sin(np.radians(ang)), 0.0,
                                                              -6 * np.cos(np.radians(ang))])
        poses[k + 1] = (R, -R @ center)
    rays, proj = {}, {}
    for i, (R, t) in poses.items():
        X = pts @ R.T + t
        rays[i] = X[:, :2] / X[:, 2:3] + rng.normal(0, NOISE_PX / FOCAL, (n_points, 2))
        proj[i] = rays[i]
    shifted = np.argmin(np.linalg.norm((pts + PERIOD)[:, None] - pts[None], axis=2), axis=1)
    matches, planted_mask = {}, {}
    for i in poses:
        for j in poses:
            if j <= i:
                continue
            idx = rng.permutation(n_points)[: n_points // 2]
            good = np.column_stack([idx, idx])
            bad_idx = rng.permutation(n_points)[: int(planted * len(idx))]
            bad = np.column_stack([bad_idx, shifted[bad_idx]])
            bad = bad[bad[:, 0] != bad[:, 1]]
            matches[(i, j)] = np.vstack([good, bad]).astype(np.int64)
            planted_mask[(i, j)] = np.r_[np.zeros(len(good), bool), np.ones(len(bad), bool)]
    focal = {i: FOCAL for i in poses}
    return poses, rays, focal, matches, planted_mask


def _pair_rotations(poses):
    return {(i, j): relative_pose(poses[i], poses[j])[0] for i in poses for j in poses if i < j}


def test_planted_wrong_matches_are_removed_and_correct_ones_kept():
    poses, rays, focal, matches, planted = _scene()
    res = check_matches(matches, rays, focal, poses, _pair_rotations(poses), MatchCheckConfig(mode="remove"))
    assert res.used and res.trusted == frozenset(poses)
    fail = np.concatenate([res.failed[p] for p in sorted(matches)])
    bad = np.concatenate([planted[p] for p in sorted(matches)])
    assert fail[~bad].mean() <= MAX_CORRECT_REMOVED
    assert 1 - fail[bad].mean() <= MAX_PLANTED_KEPT
    assert not res.wrong_pairs  # every pair is mostly right
    # the threshold follows the residuals: noise of 0.5 px gives a threshold of a few px
    assert 1.0 <= res.threshold_px <= 4.0


def test_a_pair_mostly_wrong_is_removed_whole():
    poses, rays, focal, matches, _ = _scene(seed=1)
    rng = np.random.default_rng(3)
    m = matches[(1, 2)]
    matches[(1, 2)] = np.column_stack([m[:, 0], rng.permutation(m[:, 1])])  # a doppelganger pair
    res = check_matches(matches, rays, focal, poses, _pair_rotations(poses), MatchCheckConfig(mode="remove"))
    assert res.wrong_pairs == ((1, 2),)
    assert res.pair_fail_share[(1, 2)] > 0.9


def test_an_image_placed_wrong_is_not_trusted_and_its_matches_not_judged():
    poses, rays, focal, matches, _ = _scene(seed=2)
    R, t = poses[4]
    poses = {**poses, 4: (_rot([0, 1, 0], 30.0) @ R, t)}  # the estimate got image 4 wrong
    true_rotations = _pair_rotations(_scene(seed=2)[0])
    res = check_matches(matches, rays, focal, poses, true_rotations, MatchCheckConfig(mode="remove"))
    assert res.used and 4 not in res.trusted and res.trusted == frozenset(poses) - {4}
    assert not any(4 in p for p in res.failed)  # kept unjudged: not removed on a wrong pose
    assert res.agreeing_pairs[4] == 0


def test_a_group_placed_wrong_together_is_not_trusted_rather_than_cut_off():
    """Images 7 and 8 placed wrong by one rigid motion agree with each other, and (as wrong pairs
    of a repeated structure can) their pairs to image 1 agree with the wrong placement: the
    trust test passes them, but judging their correct pairs would remove every pair that joins
    them to the rest. They are not trusted, and nothing of theirs is removed."""
    poses, rays, focal, matches, _ = _scene(seed=6)
    rotations = _pair_rotations(poses)
    move = _rot([1, 0, 0], 40.0)
    bad = {**poses, **{k: (poses[k][0] @ move, poses[k][1] + np.array([0.0, 2.0, 0.0])) for k in (7, 8)}}
    for k in (7, 8):
        rotations[(1, k)] = relative_pose(bad[1], bad[k])[0]  # a wrong pair that agrees with the wrong group
    plain = check_matches(matches, rays, focal, bad, rotations,
                          MatchCheckConfig(mode="remove"))
    assert plain.used and plain.cut_off == frozenset({7, 8})
    assert plain.trusted == frozenset(poses) - {7, 8}
    assert not any(7 in p or 8 in p for p in plain.failed) and not plain.wrong_pairs


def test_cut_off_images_follow_the_pair_graph():
    m = {p: np.zeros((20, 2), np.int64) for p in [(1, 2), (2, 3), (3, 4), (4, 5), (1, 5)]}
    none = {p: np.zeros(20, bool) for p in m}
    assert cut_off_images(m, none, (), 15) == set()
    assert cut_off_images(m, none, ((3, 4),), 15) == set()  # still joined the other way round
    assert cut_off_images(m, none, ((2, 3), (3, 4)), 15) == {3}
    most_fail = {**none, (2, 3): np.r_[np.ones(10, bool), np.zeros(10, bool)]}
    assert cut_off_images(m, most_fail, ((3, 4),), 15) == {3}  # 10 left: below 15, no link
    assert cut_off_images(m, most_fail, ((3, 4),), 10) == set()


def test_an_estimate_wrong_as_a_whole_removes_nothing():
    poses, rays, focal, matches, _ = _scene(seed=3)
    true_rotations = _pair_rotations(poses)
    rng = np.random.default_rng(0)
    bad = {i: (_rot(rng.normal(size=3), 40 + 75 * rng.random()) @ R, t) for i, (R, t) in poses.items()}
    res = check_matches(matches, rays, focal, bad, true_rotations, MatchCheckConfig(mode="remove"))
    assert not res.used and res.reason and not res.failed and not res.wrong_pairs


def test_too_few_placed_images_remove_nothing():
    poses, rays, focal, matches, _ = _scene(seed=4)
    two = {i: poses[i] for i in (1, 2)}
    res = check_matches(matches, rays, focal, two, _pair_rotations(poses), MatchCheckConfig(mode="remove"))
    assert not res.used and "2 images" in res.reason


def test_trust_counts_agreeing_pairs():
    poses, *_ = _scene(seed=5, n_images=4)
    rot = _pair_rotations(poses)
    rot[(1, 2)] = _rot([1, 0, 0], 20.0) @ rot[(1, 2)]  # a wrong pair's own rotation
    trusted, agree, total = trusted_images(poses, rot, 5.0, 2)
    assert trusted == {1, 2, 3, 4}
    assert agree[1] == 2 and total[1] == 3


def test_distances_and_threshold():
    R, t = np.eye(3), np.array([1.0, 0.0, 0.0])
    E = essential((R, t))
    y1 = np.array([[0.1, 0.2], [0.0, 0.0]])
    y2 = np.array([[0.3, 0.2], [0.5, 0.1]])  # the first on its epipolar line (same row), the second 0.1 off
    d = symmetric_epipolar_distance(E, y1, y2)
    assert d[0] == pytest.approx(0.0, abs=1e-12) and d[1] == pytest.approx(0.1)
    assert symmetric_epipolar_distance(np.zeros((3, 3)), y1, y2).tolist() == [np.inf, np.inf]
    rng = np.random.default_rng(0)
    sample = rng.exponential(0.5, 200_000)
    assert robust_scale(sample) == pytest.approx(0.5, rel=0.02)
    assert threshold_px(0.5, 0.0027, 0.1, 100.0) == pytest.approx(0.5 * np.log(1 / 0.0027))
    assert np.mean(sample > threshold_px(robust_scale(sample), 0.0027, 0.1, 100.0)) == pytest.approx(0.0027, abs=0.001)
    assert threshold_px(0.01, 0.0027, 1.0, 4.0) == 1.0 and threshold_px(10.0, 0.0027, 1.0, 4.0) == 4.0


@pytest.mark.parametrize("field, value", [("false_reject", 0.0), ("false_reject", 0.5), ("min_threshold_px", 5.0),
                                          ("max_rounds", 0), ("estimate_matches_per_image", -1), ("mode", "maybe")])
def test_config_refuses_bad_values(field, value):
    with pytest.raises(ValueError):
        MatchCheckConfig(**{field: value})


class _Scripted:
    """An estimator that hands out prepared estimates, one per round (empty once they run out),
    and places no image."""

    def __init__(self, *estimates):
        self.estimates = list(estimates)
        self.calls = 0
        self.given: list[set] = []  # the pairs each estimate was asked from

    def estimate(self, matches):
        self.calls += 1
        self.given.append(set(matches))
        return self.estimates.pop(0) if self.estimates else _Estimate(failure="no model (scripted)")

    def place(self, estimate, image_id, matches, trusted, min_inliers=None):
        return None


class _Estimate:
    def __init__(self, poses=None, rays=None, focal=None, pair_rotations=None, failure=""):
        self.poses, self.rays, self.focal = poses or {}, rays or {}, focal or {}
        self.pair_rotations, self.failure, self.seconds = pair_rotations or {}, failure, {"mapper": 0.0}
        self.mapper_steps = {}


def test_rounds_judge_and_a_later_round_that_fails_keeps_the_first_verdicts():
    poses, rays, focal, matches, planted = _scene(seed=2)
    R, t = poses[4]
    wrong4 = {**poses, 4: (_rot([0, 1, 0], 30.0) @ R, t)}  # image 4 untrusted: a second round is asked for
    first = _Estimate(wrong4, rays, focal, _pair_rotations(poses))
    est = _Scripted(first)
    d = judge_in_rounds(matches, est, MatchCheckConfig(mode="remove", max_rounds=2))
    assert est.calls == 2 and d.rounds == 2
    assert d.used and d.registered == frozenset(poses) and d.untrusted == frozenset({4})
    assert d.trusted == frozenset(poses) - {4}
    assert d.reason.startswith("round 2: ") and "no model (scripted)" in d.reason
    bad = np.concatenate([planted[p] for p in sorted(d.judged_pairs)])
    fail = np.concatenate([d.failed[p] for p in sorted(d.judged_pairs)])
    assert 1 - fail[bad].mean() <= MAX_PLANTED_KEPT
    assert not any(4 in p for p in d.failed)  # never judged: its pose was not trusted
    assert len(d.seconds) == 2 and {"mapper", "judging", "placements"} <= set(d.seconds[0])


def test_images_around_walks_the_pair_graph():
    chain = [(1, 2), (2, 3), (3, 4), (4, 5), (5, 6)]
    assert images_around({1}, chain, 0) == {1}
    assert images_around({1}, chain, 2) == {1, 2, 3}
    assert images_around({3, 6}, chain, 1) == {2, 3, 4, 5, 6}
    assert images_around({9}, chain, 2) == {9}  # an image without pairs is itself


def test_a_later_round_estimates_only_around_the_images_not_trusted():
    """A sparse pair graph (each image with the next two): one image placed wrong asks for a
    second round, which is estimated only from the pairs among the images two pairs around it,
    and judges only its pairs; the first round's verdicts stay."""
    poses, rays, focal, matches, planted = _scene(seed=2, n_images=12)
    matches = {p: m for p, m in matches.items() if p[1] - p[0] <= 2}
    planted = {p: planted[p] for p in matches}
    R, t = poses[2]
    first = _Estimate({**poses, 2: (_rot([0, 1, 0], 30.0) @ R, t)}, rays, focal, _pair_rotations(poses))
    second = _Estimate(poses, rays, focal, _pair_rotations(poses))
    est = _Scripted(first, second)
    d = judge_in_rounds(matches, est, MatchCheckConfig(mode="remove", max_rounds=2))
    assert est.calls == 2 and d.rounds == 2 and d.used
    assert est.given[0] == set(matches)
    near = images_around({2}, matches, LATER_ROUND_RINGS)
    assert near == {1, 2, 3, 4, 5, 6}
    assert est.given[1] == {p for p in matches if p[0] in near and p[1] in near}
    assert len({i for p in est.given[1] for i in p}) == 6 < len(poses)  # not the whole pair graph
    assert d.trusted == frozenset(poses) and not d.untrusted
    assert {p for p in d.failed if 2 in p} == {p for p in matches if 2 in p}  # judged in round 2
    bad = np.concatenate([planted[p] for p in sorted(d.judged_pairs)])
    fail = np.concatenate([d.failed[p] for p in sorted(d.judged_pairs)])
    assert 1 - fail[bad].mean() <= MAX_PLANTED_KEPT
    assert fail[~bad].mean() <= MAX_CORRECT_REMOVED


def test_an_estimator_that_places_nothing_says_why():
    _, _, _, matches, _ = _scene(seed=2)
    d = judge_in_rounds(matches, _Scripted(), MatchCheckConfig(mode="remove"))
    assert not d.used and not d.failed and "placed 0 images" in d.reason and "no model (scripted)" in d.reason
