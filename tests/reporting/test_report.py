"""report on a synthetic scene against its exact GT; metrics react to a perturbed GT."""

from __future__ import annotations

import json

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.geometry import project_to_so3
from colmap_miho.reporting import gt_model as gm
from colmap_miho.reporting import model_errors
from colmap_miho.reporting import report as rp
from colmap_miho.sfm import run_mapping
from miho_bench.synthetic import make_synthetic_scene

# Measured on this scene (0.5 px noise, 10% outliers): model pose errors < 0.5 deg, AUC@5 ~0.93.
MODEL_AUC5_MIN = 0.85
TWO_VIEW_AUC20_MIN = 0.8


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    root = tmp_path_factory.mktemp("rep")
    scene = make_synthetic_scene(root / "scene", num_images=6, num_points=300, outlier_ratio=0.1,
                                 noise_px=0.5, render_images=False, seed=1)
    run_mapping(scene.database, scene.image_dir, root / "model", seed=0)
    gt_dir = root / "gt"
    gt_dir.mkdir()
    scene.gt_reconstruction.write_text(str(gt_dir))
    return scene, root / "model", gt_dir


def test_report_json_keys_and_high_auc(mapped, tmp_path):
    scene, model, gt = mapped
    out = tmp_path / "r.json"
    before = scene.database.read_bytes()
    assert main(["report", "--model", str(model), "--database", str(scene.database), "--gt", str(gt),
                 "--json", str(out), "-q"]) == 0
    r = json.loads(out.read_text())
    # the database is read through a copy: unchanged and no SQLite side files left behind
    assert scene.database.read_bytes() == before
    assert not any(scene.database.with_name(scene.database.name + s).exists() for s in ("-wal", "-shm"))
    for k in ("num_images", "num_reg_images", "num_points3D", "num_observations", "mean_track_length",
              "mean_reprojection_error"):
        assert k in r["reconstruction"]
    assert r["reconstruction"]["num_reg_images"] == 6
    for sec in ("model_pose_auc", "two_view_pose_auc_E", "two_view_pose_auc_F"):
        for k in ("auc5", "auc10", "auc20"):
            assert 0.0 <= r[sec][k] <= 1.0
    assert r["model_pose_auc"]["auc5"] > MODEL_AUC5_MIN
    assert r["model_pose_auc"]["num_pairs"] == 15
    assert r["two_view_pose_auc_E"]["auc20"] > TWO_VIEW_AUC20_MIN
    assert r["two_view_pose_auc_F"]["num_pairs"] == 15
    assert r["absolute"]["rotation_error_deg"]["median"] < 0.5
    assert len(r["pairs"]) == 15


def test_perturbed_gt_lowers_auc(mapped, tmp_path):
    _, model, gt = mapped
    good = rp.build_report(model, gt=gt)
    poses = gm.load_gt_poses(gt)
    import cv2

    name = sorted(poses)[0]
    p = poses[name]
    R_bad = cv2.Rodrigues(np.array([0.0, np.radians(8.0), 0.0]))[0] @ p.R
    poses[name] = gm.CameraPose(name=name, K=p.K, R=R_bad, t=p.t, width=p.width, height=p.height)
    gm.write_colmap_model(poses, tmp_path / "bad")
    bad = rp.build_report(model, gt=tmp_path / "bad")
    # 5 of 15 pairs contain the rotated camera: their error is >= ~8 deg, beyond AUC@5
    assert bad["model_pose_auc"]["auc5"] < good["model_pose_auc"]["auc5"] - 0.25
    assert bad["absolute"]["rotation_error_deg"]["max"] > 5.0


def test_unregistered_image_counts_as_failure():
    rng = np.random.default_rng(0)
    K = np.eye(3)
    gt = {f"{i}.png": gm.CameraPose(name=f"{i}.png", K=K, R=np.eye(3), t=rng.normal(size=3), width=10, height=10)
          for i in range(4)}
    est = dict(gt)
    est.pop("3.png")
    errs = model_errors.model_pair_errors(est, gt)
    assert len(errs) == 6 and sum(np.isinf(list(errs.values()))) == 3
    # identical poses: arccos of 1 - 1 ulp is already 1.2e-6 degrees
    assert max(e for e in errs.values() if np.isfinite(e)) < 1e-4


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    R = project_to_so3(rng.normal(size=(3, 3)))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 3.0])
    s, R_est, t = model_errors.umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1, -2, 3])


def test_report_without_gt_and_bad_model(mapped, tmp_path, capsys):
    _, model, _ = mapped
    argv = ["report", "--model", str(model), "--ply", str(tmp_path / "p.ply"), "--json", str(tmp_path / "r.json")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "images registered" in out and "sparse cloud" in out
    assert (tmp_path / "p.ply").read_bytes().startswith(b"ply")
    r = json.loads((tmp_path / "r.json").read_text())
    assert "model_pose_auc" not in r and r["pointcloud"]["num_points"] == r["reconstruction"]["num_points3D"]
    assert main(["report", "--model", str(tmp_path / "missing"), "-q"]) == 2
