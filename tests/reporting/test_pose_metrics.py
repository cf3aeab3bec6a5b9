"""Pose errors, AUC/mAA by hand, and the two-view E/F protocols on synthetic cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest

from colmap_miho.geometry import relative_pose
from colmap_miho.reporting import pose_metrics as pm


def rot(axis, deg):
    import cv2

    v = np.asarray(axis, dtype=np.float64)
    v = v / np.linalg.norm(v) * math.radians(deg)
    return cv2.Rodrigues(v)[0]


# ---------------------------------------------------------------- errors
def test_rotation_error_known_angle():
    assert pm.rotation_error_deg(rot([0, 0, 1], 7.0), np.eye(3)) == pytest.approx(7.0, abs=1e-9)
    assert pm.rotation_error_deg(rot([1, 2, 3], 33.0), rot([1, 2, 3], 3.0)) == pytest.approx(30.0, abs=1e-9)


def test_translation_angle_fold_and_degenerate():
    assert pm.translation_angle_deg([1, 0, 0], [0, 1, 0]) == pytest.approx(90.0)
    # 170 deg apart: folded 10, unfolded 170
    t = [math.cos(math.radians(170)), math.sin(math.radians(170)), 0]
    assert pm.translation_angle_deg(t, [1, 0, 0]) == pytest.approx(10.0)
    assert pm.translation_angle_deg(t, [1, 0, 0], fold=False) == pytest.approx(170.0)
    assert pm.translation_angle_deg([0, 0, 0], [1, 0, 0]) == math.inf
    with pytest.raises(ValueError, match="translations"):
        pm.translation_angle_deg([1, 0], [1, 0, 0])


def test_relative_pose_and_pose_error():
    R1, t1 = rot([0, 1, 0], 10), np.array([0.1, 0.2, 0.3])
    R2, t2 = rot([1, 0, 0], -20), np.array([1.0, -0.5, 2.0])
    R, t = relative_pose((R1, t1), (R2, t2))
    X = np.array([0.3, -1.2, 4.0])
    np.testing.assert_allclose(R @ (R1 @ X + t1) + t, R2 @ X + t2, atol=1e-12)
    # rotation error 4 deg, translation exact -> 4
    assert pm.pose_error_deg(rot([0, 0, 1], 4) @ R, t, R, t) == pytest.approx(4.0, abs=1e-9)


# ---------------------------------------------------------------- AUC / mAA by hand
def test_auc_by_hand():
    # errors [1, 2, inf], threshold 5: curve (0,0) (1,1/3) (2,2/3) flat to 5 at 2/3.
    # area = 1*(1/3)/2 + 1*(1/3+2/3)/2 + 3*(2/3) = 1/6 + 1/2 + 2 = 8/3 ; /5 = 8/15
    assert pm.pose_auc([1.0, 2.0, math.inf], [5.0]) == pytest.approx([8 / 15], abs=1e-12)
    # threshold 1.5 falls between errors 1 and 2: like the SuperGlue/LoFTR reference code the
    # curve is closed with the last reached recall (1/3) -> (0,0) (1,1/3) (1.5,1/3)
    # area = 1/6 + 0.5 * 1/3 = 1/3 ; /1.5 = 2/9
    assert pm.pose_auc([1.0, 2.0, math.inf], [1.5]) == pytest.approx([2 / 9], abs=1e-12)
    # all perfect -> 1, all failed -> 0, empty -> 0
    assert pm.pose_auc([0.0, 0.0], [5, 10]) == pytest.approx([1.0, 1.0])
    assert pm.pose_auc([math.inf, float("nan")], [5]) == [0.0]
    assert pm.pose_auc([], [5]) == [0.0]
    with pytest.raises(ValueError, match="positive"):
        pm.pose_auc([1.0], [0.0])


def test_maa_by_hand():
    # [1, 2, inf] over t = 1..10 with err < t: t=1 -> 0, t=2 -> 1/3, t=3..10 -> 2/3 (8 times)
    # mean = (0 + 1/3 + 16/3) / 10 = 17/30
    assert pm.mean_average_accuracy([1.0, 2.0, math.inf]) == pytest.approx(17 / 30)
    assert pm.mean_average_accuracy([]) == 0.0


def test_auc_summary_keys():
    s = pm.auc_summary([1.0, 2.0, math.inf])
    assert set(s) == {"auc5", "auc10", "auc20", "maa", "num_pairs", "num_failed"}
    assert s["auc5"] == pytest.approx(8 / 15) and s["num_failed"] == 1 and s["num_pairs"] == 3


# ---------------------------------------------------------------- two-view protocols
def _two_view(n=300, noise=0.3, outlier_ratio=0.0, seed=0):
    rng = np.random.default_rng(seed)
    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    X = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 8, n)]
    R = rot([0.2, 1.0, 0.1], 12.0)
    t = np.array([-1.0, 0.1, 0.2])

    def project(Xc):
        x = (K @ Xc.T).T
        return x[:, :2] / x[:, 2:]

    p1 = project(X) + rng.normal(0, noise, (n, 2))
    p2 = project((R @ X.T).T + t) + rng.normal(0, noise, (n, 2))
    n_out = int(outlier_ratio * n)
    p2[:n_out] = rng.uniform([0, 0], [640, 480], (n_out, 2))
    return p1, p2, K, R, t


# Measured: with 0.3 px noise both protocols land at 0.1-0.3 deg; 1 deg leaves margin.
POSE_TOL_DEG = 1.0


@pytest.mark.parametrize("outliers", [0.0, 0.3])
def test_essential_protocol_recovers_pose(outliers):
    p1, p2, K, R, t = _two_view(outlier_ratio=outliers)
    res = pm.pose_from_essential(p1, p2, K, K, R, t)
    assert res.success
    assert res.error_deg < POSE_TOL_DEG
    # recoverPose gives the sign too: unfolded translation error is small as well
    assert pm.translation_angle_deg(res.t, t, fold=False) < POSE_TOL_DEG


def test_fundamental_protocol_with_and_without_magsac():
    p1, p2, K, R, t = _two_view(outlier_ratio=0.0)
    assert pm.pose_from_fundamental(p1, p2, K, K, R, t, magsac=False).error_deg < POSE_TOL_DEG
    p1, p2, K, R, t = _two_view(outlier_ratio=0.3, seed=1)
    with_magsac = pm.pose_from_fundamental(p1, p2, K, K, R, t, magsac=True)
    without = pm.pose_from_fundamental(p1, p2, K, K, R, t, magsac=False)
    assert with_magsac.success and with_magsac.error_deg < POSE_TOL_DEG
    assert with_magsac.num_inliers < with_magsac.num_matches
    # plain 8-point on 30% outliers is far off: MAGSAC is what makes the difference
    assert without.error_deg > 5 * with_magsac.error_deg


def test_protocols_report_failure_not_raise():
    p1, p2, K, R, t = _two_view(n=4)
    assert not pm.pose_from_essential(p1, p2, K, K, R, t).success
    res = pm.pose_from_fundamental(p1, p2, K, K, R, t)
    assert not res.success and res.error_deg == math.inf and "8" in res.reason
    with pytest.raises(ValueError, match="pts1"):
        pm.pose_from_essential(p1[:, :1], p2, K, K, R, t)
