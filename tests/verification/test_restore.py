"""Restoring the filter's removals: cameras along a horizontal baseline (a facade's street),
correct matches and wrong ones lying exactly on their epipolar line (the repeated-structure
error); only a third image that sees depth can tell them apart."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.verification.restore import restore_matches

FOCAL = 1000.0
THRESHOLD_PX = 2.0


def _camera(centre) -> tuple[np.ndarray, np.ndarray]:
    R = np.eye(3)
    return R, -R @ np.asarray(centre, float)


def _project(pose, X) -> np.ndarray:
    Y = X @ pose[0].T + pose[1]
    return Y[:, :2] / Y[:, 2:]


@pytest.fixture
def street():
    """Poses of images 0..3 (0-2 on one line, 3 above the line), points, their rays, and wrong
    matches in image 1: keypoints N..2N-1 where each point seen from image 0 would be at 1.25x
    its depth (on the epipolar line of its keypoint in image 0)."""
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -2, 8], [2, 2, 12], (60, 3))
    poses = {0: _camera([-1.5, 0, 0]), 1: _camera([1.5, 0, 0]), 2: _camera([0.0, 0, 0]), 3: _camera([0, 1.5, 0])}
    c0 = np.array([-1.5, 0, 0])
    far = c0 + 1.25 * (X - c0)
    rays = {i: _project(p, X) for i, p in poses.items()}
    rays[1] = np.concatenate([rays[1], _project(poses[1], far)])
    n = len(X)
    correct = np.column_stack([np.arange(n), np.arange(n)])
    wrong = np.column_stack([np.arange(n), n + np.arange(n)])
    return poses, rays, correct, wrong


def _restore(street, kept, candidates):
    poses, rays, _, _ = street
    return restore_matches(candidates, kept, rays, {i: FOCAL for i in poses}, poses, set(poses), THRESHOLD_PX)


def test_correct_matches_come_back_and_matches_on_the_epipolar_line_do_not(street):
    _, _, correct, wrong = street
    kept = {(0, 3): correct, (1, 3): correct}  # the third image sees depth: it is off the baseline
    out = _restore(street, kept, {(0, 1): np.concatenate([correct, wrong])})
    ok = out[(0, 1)]
    assert ok[: len(correct)].all() and not ok[len(correct):].any()


def test_the_epipolar_test_alone_restores_nothing(street):
    _, _, correct, wrong = street
    assert _restore(street, {}, {(0, 1): np.concatenate([correct, wrong])}) == {}


def test_a_third_image_that_sees_little_depth_proves_nothing(street):
    """A third image right beside image 0 sees the depth error of a wrong match in image 1 about
    60 times smaller: it proves nothing, correct or not."""
    poses, rays, correct, wrong = street
    poses = {**poses, 4: _camera([-1.45, 0, 0])}
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -2, 8], [2, 2, 12], (60, 3))  # the fixture's points
    rays = {**rays, 4: _project(poses[4], X)}
    out = restore_matches({(0, 1): np.concatenate([correct, wrong])}, {(0, 4): correct}, rays,
                          {i: FOCAL for i in poses}, poses, set(poses), THRESHOLD_PX)
    assert out == {}


def test_a_match_joining_two_tracks_that_share_an_image_is_not_restored(street):
    _, _, correct, _ = street
    # keypoint 0 of image 1 is already in the track of point 1 (through image 3's keypoint 1):
    # giving back (0, 0) - (1, 0) would put keypoints 0 and 1 of image 3 in one track
    kept = {(0, 3): correct, (1, 3): np.array([[0, 1]] + [[k, k] for k in range(1, len(correct))])}
    out = _restore(street, kept, {(0, 1): correct[:1]})
    assert (0, 1) not in out


def test_a_keypoint_in_no_track_joins_one_track_only():
    """Keypoint 5 of image 0 is in no kept track; restored to the track of image 1's keypoint 0,
    it may not then join the track of image 2's keypoint 0 too: both hold a keypoint of image 3."""
    from colmap_miho.verification.restore import _kept_ends, _track_consistent

    kept = {(1, 3): np.array([[0, 0]]), (2, 3): np.array([[0, 1]])}
    ends = _kept_ends(kept, {0, 1, 2, 3})
    candidates = {(0, 1): np.array([[5, 0]]), (0, 2): np.array([[5, 0]])}
    out = _track_consistent({p: np.ones(1, bool) for p in candidates}, candidates, ends)
    assert list(out) == [(0, 1)]


def test_links_are_gathered_and_indexed_per_image():
    """The batched third-image links read each link's own ray and camera, whatever the order of
    the images and whether an image has a pose."""
    from colmap_miho.verification.restore import _Cameras, _gather

    rng = np.random.default_rng(3)
    rays = {7: rng.normal(size=(5, 2)), 2: rng.normal(size=(4, 2)), 11: rng.normal(size=(3, 2))}
    image = np.array([11, 7, 2, 7, 11, 2, 2])
    kp = np.array([2, 4, 0, 1, 0, 3, 3])
    expected = np.array([rays[int(i)][int(k)] for i, k in zip(image, kp, strict=True)])
    assert np.array_equal(_gather(rays, image, kp), expected)
    poses = {7: _camera([1.0, 0, 0]), 2: _camera([0, 2.0, 0])}
    cams = _Cameras.of(poses, {7: 900.0, 2: 1100.0})
    at, posed = cams.index(np.array([2, 11, 7, 1, 7]))
    assert posed.tolist() == [True, False, True, False, True]
    assert np.array_equal(cams.t[at[0]], poses[2][1]) and np.array_equal(cams.t[at[2]], poses[7][1])
    assert cams.f[at[4]] == 900.0
