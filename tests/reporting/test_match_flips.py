"""Turned-wrong / turned-right matches under GT geometry: two views with exact keypoints, moved
across or along their epipolar lines by known amounts."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.geometry import fundamental_from_poses
from colmap_miho.reporting import match_flips as mf
from colmap_miho.reporting.demo_scene import look_at
from colmap_miho.reporting.gt_model import CameraPose

N = 200
MOVE_PX = 9.0  # far beyond the 4 px threshold across the line


def _two_views():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    cams = {}
    for name, x in (("a", -0.4), ("b", 0.4)):
        R, t = look_at(np.array([x, 0.1, 0.0]), np.array([0.0, 0.0, 6.0]))
        cams[name] = CameraPose(name=name, K=K, R=R, t=t, width=640, height=480)
    rng = np.random.default_rng(0)
    X = rng.uniform([-1.0, -0.8, 5.0], [1.0, 0.8, 7.0], size=(N, 3))
    kps = {}
    for name, cam in cams.items():
        p = (cam.K @ (cam.R @ X.T + cam.t[:, None])).T
        kps[name] = p[:, :2] / p[:, 2:3]
    return cams, kps


def _line_normal(cams, kps):
    """Unit normal (N, 2) of the epipolar line in image b of every keypoint of image a."""
    F = fundamental_from_poses(cams["a"].K, cams["a"].R, cams["a"].t, cams["b"].K, cams["b"].R, cams["b"].t)
    lines = np.column_stack([kps["a"], np.ones(N)]) @ F.T
    return lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)


def test_counts_across_and_along_the_epipolar_line():
    cams, kps = _two_views()
    normal = _line_normal(cams, kps)
    along = normal[:, ::-1] * np.array([1.0, -1.0])
    before = {k: v.copy() for k, v in kps.items()}
    after = {k: v.copy() for k, v in kps.items()}
    wrong, still, right = np.arange(0, 10), np.arange(10, 30), np.arange(30, 35)
    after["b"][wrong] += MOVE_PX * normal[wrong]  # correct -> off the line: turned wrong
    after["b"][still] += MOVE_PX * along[still]  # moved along the line: still correct
    before["b"][right] += MOVE_PX * normal[right]  # off the line before, exact after
    idx = np.column_stack([np.arange(N), np.arange(N)])
    matches_before = {("a", "b"): idx}
    matches_after = {("a", "b"): idx[:-3]}  # the last 3 only before: not compared
    cases = mf.epipolar_flip_cases(cams, before, after, matches_before, matches_after)
    assert cases.before.size == N - 3 and cases.pairs == [("a", "b")]
    assert np.array_equal(np.flatnonzero(cases.turned_wrong()), wrong)
    assert np.array_equal(np.flatnonzero(cases.turned_right()), right)
    s = mf.epipolar_flips(cams, before, after, matches_before, matches_after)
    assert (s.num_compared, s.num_turned_wrong, s.num_turned_right) == (N - 3, wrong.size, right.size)
    assert s.num_moved == wrong.size + still.size + right.size
    assert s.wrong_disp_median_px == pytest.approx(MOVE_PX) and s.wrong_disp_max_px == pytest.approx(MOVE_PX)
    assert s.right_disp_median_px == pytest.approx(MOVE_PX)
    # a threshold beyond every move counts nothing
    assert mf.summarize_flips(cases, 3 * MOVE_PX).num_turned_wrong == 0
    assert s.to_dict()["num_turned_wrong"] == wrong.size


def test_nothing_moved_and_bad_input():
    cams, kps = _two_views()
    idx = np.column_stack([np.arange(N), np.arange(N)])
    s = mf.epipolar_flips(cams, kps, kps, {("a", "b"): idx}, {("a", "b"): idx})
    assert s.num_turned_wrong == s.num_turned_right == s.num_moved == 0
    assert s.to_dict()["wrong_disp_median_px"] is None
    # pairs with an image outside the GT are skipped
    assert mf.epipolar_flips({"a": cams["a"]}, kps, kps, {("a", "b"): idx}, {("a", "b"): idx}).num_compared == 0
    with pytest.raises(ValueError, match="another shape"):
        mf.epipolar_flips(cams, kps, {"a": kps["a"], "b": kps["b"][:-1]}, {("a", "b"): idx}, {("a", "b"): idx})
    with pytest.raises(ValueError, match="threshold_px"):
        mf.epipolar_flips(cams, kps, kps, {("a", "b"): idx}, {("a", "b"): idx}, threshold_px=0.0)
