"""compare: both reports, tables and plots; the input database is untouched."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.reporting.compare import comparison_markdown, match_changes
from miho_bench.synthetic import make_synthetic_scene

# Measured on this synthetic scene (0.5 px noise, 20% planted outliers in the verified
# matches): model pose AUC@5 ~0.99 on both sides.
SYN_MODEL_AUC5_MIN = 0.9


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    s = make_synthetic_scene(root / "scene", num_images=5, num_points=250, outlier_ratio=0.2, noise_px=0.5, seed=2)
    gt = root / "gt"
    gt.mkdir()
    s.gt_reconstruction.write_text(str(gt))
    return s, gt


def test_compare_synthetic(scene, tmp_path, capsys):
    """Filter-only recipe: NCC refinement end to end is covered by tests/reporting/test_demo.py (it costs
    about 0.1 s per keypoint on 2 busy cores today, too slow to run twice)."""
    s, gt = scene
    before = sha(s.database)
    out = tmp_path / "cmp"
    rc = main(["compare", "--database", str(s.database), "--images", str(s.image_dir), "--output", str(out),
               "--gt", str(gt), "--workers", "1", "--set", "pipeline.refine_keypoints=false"])
    assert rc == 0
    assert sha(s.database) == before
    printed = capsys.readouterr().out
    assert "compare.md" in printed and "pose_error_curves.png" in printed
    cmp = json.loads((out / "compare.json").read_text())
    for side in ("baseline", "refined"):
        rep = json.loads((out / side / "report.json").read_text())
        assert rep["reconstruction"]["num_reg_images"] == 5
        assert rep["model_pose_auc"]["auc5"] > SYN_MODEL_AUC5_MIN
        assert {"auc5", "auc10", "auc20", "num_pairs"} <= set(rep["two_view_pose_auc_E"])
        assert {"auc5", "auc10", "auc20", "num_pairs"} <= set(rep["two_view_pose_auc_F"])
        assert cmp[side]["model_pose_auc"] == rep["model_pose_auc"]
    # the filter removes planted outliers: fewer verified matches after, never more
    before_m, after_m = cmp["matches_per_pair"]["baseline"], cmp["matches_per_pair"]["refined"]
    assert sum(after_m.values()) < sum(before_m.values())
    assert all(after_m.get(k, 0) <= v for k, v in before_m.items())
    # same pairs evaluated on both sides
    assert cmp["baseline"]["two_view_pose_auc_E"]["num_pairs"] == cmp["refined"]["two_view_pose_auc_E"]["num_pairs"]
    for png in ("pose_error_curves.png", "keypoint_displacement.png", "matches_per_pair.png"):
        assert (out / "plots" / png).stat().st_size > 5000
    # keypoint accuracy on both sides; planted outliers join tracks, the filter splits them again
    kb, kr = cmp["baseline"]["keypoint_accuracy"], cmp["refined"]["keypoint_accuracy"]
    assert kr["num_measured_tracks"] > kb["num_measured_tracks"]
    assert kr["epipolar_share_above"] < kb["epipolar_share_above"]
    rows = {r["metric"]: r for r in cmp["rows"]}
    assert rows["GT track residual median (px)"]["refined"] == f"{kr['residual_median_px']:.3f}"
    assert "epipolar distance median (px)" in printed and "wrong tracks > 4 px (%)" in printed
    # no keypoint moved: every kept match is compared, none turned wrong or right
    flips = cmp["refined"]["epipolar_flips"]
    assert flips["num_compared"] == sum(after_m.values()) and flips["num_moved"] == 0
    assert flips["num_turned_wrong"] == flips["num_turned_right"] == 0


def test_match_changes_sees_moved_keypoints(scene, tmp_path):
    import shutil

    import pycolmap

    s, _ = scene
    copy = tmp_path / "moved.db"
    shutil.copyfile(s.database, copy)
    with pycolmap.Database.open(str(copy)) as db:
        img = db.read_all_images()[0]
        kp = db.read_keypoints(img.image_id).copy()
        kp[:3, 0] += 0.75  # move three keypoints by 0.75 px
        db.update_keypoints(img.image_id, kp)
    ch = match_changes(s.database, copy)
    np.testing.assert_allclose(np.sort(ch["displacements"]), [0.75] * 3, atol=1e-4)
    assert ch["matches_before"] == ch["matches_after"]


def test_markdown_marks_missing_values():
    md = comparison_markdown({"reconstruction": {"num_reg_images": 3}}, {"reconstruction": {"num_reg_images": 4},
                             "model_pose_auc": {"auc5": 0.5}}, {})
    assert "| registered images | 3 | 4 |" in md and "| model pose AUC@5 (%) | - | 50.0 |" in md


@pytest.mark.slow
def test_compare_middlebury_temple(shared_data, tmp_path):
    """Real data: SIFT + exhaustive matching, then compare (filter only, to stay fast)."""
    from colmap_miho.sfm.extraction import extract_and_match

    root = shared_data / "middlebury_temple_sparse_ring"
    db = tmp_path / "db.db"
    extract_and_match(root / "images", db, max_features=4096)
    out = tmp_path / "cmp"
    rc = main(["compare", "--database", str(db), "--images", str(root / "images"), "--output", str(out),
               "--gt", str(root), "-q", "--set", "pipeline.refine_keypoints=false"])
    assert rc == 0
    for side in ("baseline", "refined"):
        rep = json.loads((out / side / "report.json").read_text())
        # about 13 of 16 register with default SIFT (data README); upside-down views fail
        assert rep["reconstruction"]["num_reg_images"] >= 10
        assert rep["two_view_pose_auc_E"]["num_pairs"] == 34  # the dataset's pairs_with_gt.txt
        assert rep["model_pose_auc"]["num_pairs"] == 120


def test_a_failing_figure_costs_only_itself(tmp_path, monkeypatch, capfd):
    """The tables and the page are written before any figure; a figure that raises is a
    warning naming it, the run still exits 0."""
    from colmap_miho.reporting import plots

    s = make_synthetic_scene(tmp_path / "scene", num_images=3, num_points=80, seed=4)

    def broken(*args, **kwargs):
        raise ValueError("no figure today")

    monkeypatch.setattr(plots, "plot_matches_per_pair", broken)
    out = tmp_path / "cmp"
    rc = main(["compare", "--database", str(s.database), "--images", str(s.image_dir), "--output", str(out),
               "--workers", "1", "--set", "pipeline.refine_keypoints=false", "-q"])
    assert rc == 0
    assert (out / "compare.md").is_file() and (out / "report.html").is_file()
    cmp = json.loads((out / "compare.json").read_text())
    assert not (out / "plots" / "matches_per_pair.png").exists()
    assert str(out / "plots" / "keypoint_displacement.png") in cmp["plots"]
    assert "figure matches_per_pair skipped: no figure today" in capfd.readouterr().err


def test_the_terminal_table_says_what_the_match_check_did():
    from colmap_miho.reporting.compare import CompareResult, format_comparison

    def text(refine):
        return format_comparison(CompareResult(output=Path("/nonexistent"), baseline={}, refined={}, refine=refine,
                                               markdown=Path("a.md"), json=Path("a.json")))

    used = {"mode": "remove", "used": True, "images": 8, "images_registered": 8, "images_trusted": ["a"] * 8,
            "matches_removed": 123, "matches_judged": 29619, "threshold_px": 2.0, "pairs_removed": 0}
    assert "Match check: global estimate of 8 of 8 images, 8 trusted; 123 of 29619 judged matches removed" \
        in text({"match_check": used})
    refused = text({"match_check": {"mode": "remove", "used": False, "reason": "bad\n\x1b[31m"}})
    assert "not used (bad\\n\\x1b[31m)" in refused  # a reason quoting names is escaped
    assert "Match check" not in text({"match_check": {}})
