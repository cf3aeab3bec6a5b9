"""The built-in demo scene: GT exactness, `demo --quick` end to end, `run` on its images."""

from __future__ import annotations

import json

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.geometry import fundamental_from_poses
from colmap_miho.reporting.demo_scene import demo_cameras, make_demo_scene
from colmap_miho.reporting.gt_model import load_gt_poses

# Measured: SIFT RANSAC inliers between rendered views lie ~0.1-0.2 px (median) from the GT
# epipolar lines; 0.5 px catches any convention slip (a 0.5 px principal-point shift or a
# wrong pose would give several pixels).
GT_EPIPOLAR_MEDIAN_MAX_PX = 0.5
# Measured on the quick demo: model pose AUC@5 ~0.99 both sides.
DEMO_MODEL_AUC5_MIN = 0.9
# Measured on the quick demo: two-view E and F AUC@10 0.94-0.96 both sides (exact GT, 6 images);
# a broken protocol or GT convention gives well under 0.5.
DEMO_TWO_VIEW_AUC10_MIN = 0.8


def test_demo_scene_gt_is_exact(tmp_path):
    import cv2

    from miho_bench.frontend import sift_matches
    from miho_bench.match_errors import epipolar_error

    scene = make_demo_scene(tmp_path, num_images=3, width=480, height=360)
    poses = load_gt_poses(scene.gt_dir)  # read back through the written COLMAP model
    names = sorted(poses)
    assert len(names) == 3 and len(list(scene.image_dir.glob("*.png"))) == 3
    for a, b in ((0, 1), (0, 2)):
        pa, pb = poses[names[a]], poses[names[b]]
        img1 = cv2.imread(str(scene.image_dir / names[a]), cv2.IMREAD_GRAYSCALE)
        img2 = cv2.imread(str(scene.image_dir / names[b]), cv2.IMREAD_GRAYSCALE)
        m = sift_matches(img1, img2, ratio=0.8, max_features=3000)
        _, mask = cv2.findFundamentalMat(m.pts1, m.pts2, cv2.USAC_MAGSAC, 1.0, 0.999, 10000)
        inl = mask.ravel().astype(bool)
        assert inl.sum() > 100
        F = fundamental_from_poses(pa.K, pa.R, pa.t, pb.K, pb.R, pb.t)
        err = epipolar_error(F, m.pts1[inl], m.pts2[inl])
        assert np.median(err) < GT_EPIPOLAR_MEDIAN_MAX_PX


def test_demo_defaults_and_bad_args(tmp_path):
    cams = demo_cameras()
    assert len(cams) == 8 and (cams[0].width, cams[0].height) == (640, 480)
    assert cams[0].K[0, 2] == pytest.approx(319.5)  # pixel-centre principal point
    with pytest.raises(ValueError, match="num_images"):
        make_demo_scene(tmp_path, num_images=2)


@pytest.mark.slow
def test_demo_quick_end_to_end(demo_run):
    rc, out = demo_run
    assert rc == 0
    cmp = json.loads((out / "compare.json").read_text())
    for side in ("baseline", "refined"):
        rep = cmp[side]
        assert rep["reconstruction"]["num_reg_images"] == 6
        assert rep["model_pose_auc"]["auc5"] > DEMO_MODEL_AUC5_MIN
        for sec in ("two_view_pose_auc_E", "two_view_pose_auc_F"):
            assert rep[sec]["auc10"] > DEMO_TWO_VIEW_AUC10_MIN
    for png in ("pose_error_curves.png", "keypoint_displacement.png", "matches_per_pair.png"):
        assert (out / "plots" / png).stat().st_size > 5000
    assert "| model pose AUC@5 (%) |" in (out / "compare.md").read_text()
    # the keypoint-accuracy rows (GT track residuals, epipolar distance) are in the demo's table
    assert "| GT track residual median (px) |" in (out / "compare.md").read_text()
    assert cmp["baseline"]["keypoint_accuracy"]["num_measured_tracks"] > 0
    assert (out / "report.html").stat().st_size > 1_000_000  # plotly's bundle is inside


@pytest.mark.slow
def test_run_on_demo_images_writes_report(demo_run, tmp_path):
    _, out = demo_run
    scene = out / "scene"
    rc = main(["run", "--images", str(scene / "images"), "--output", str(tmp_path / "w"), "--gt",
               str(scene / "gt_model"), "-q", "--workers", "1", "--max-features", "1024",
               "--set", "pipeline.refine_keypoints=false"])  # NCC refinement is covered by the demo test
    assert rc == 0
    rep = json.loads((tmp_path / "w" / "report.json").read_text())
    assert rep["reconstruction"]["num_reg_images"] == 6
    assert rep["model_pose_auc"]["auc5"] > DEMO_MODEL_AUC5_MIN
    assert {"auc5", "auc10", "auc20", "num_pairs"} <= set(rep["two_view_pose_auc_E"])
    assert (tmp_path / "w" / "refined" / "model" / "images.bin").is_file()


def test_run_fails_cleanly_on_empty_folder(tmp_path):
    (tmp_path / "imgs").mkdir()
    assert main(["run", "--images", str(tmp_path / "imgs"), "--output", str(tmp_path / "w"), "-q"]) == 1
