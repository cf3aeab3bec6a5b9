"""Mapping with known cameras (camera_model / camera_params / refine_intrinsics), the GT cameras
in compare, repeated runs, and the AUC thresholds of the reports."""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import shutil

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.reporting import pose_metrics as pm
from colmap_miho.reporting.report import (
    DEFAULT_AUC_THRESHOLDS_DEG,
    auc_key,
    auc_thresholds,
    build_report,
)
from colmap_miho.sfm import (
    MappingConfig,
    RefineIntrinsics,
    parse_camera_params,
    run_mapping,
)
from miho_bench.synthetic import make_synthetic_scene

WIDTH, HEIGHT = 640, 480
FOCAL = 1.2 * WIDTH  # make_synthetic_scene's default
# given intrinsics that differ from the truth: 1% focal, a principal point 6 px / 4 px off centre
GIVEN = (FOCAL * 1.01, FOCAL * 1.01 + 2.0, WIDTH / 2 + 6.0, HEIGHT / 2 - 4.0)


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("known")
    s = make_synthetic_scene(root / "scene", num_images=6, num_points=300, outlier_ratio=0.1, noise_px=0.5,
                             render_images=True, seed=4)
    gt = root / "gt"
    gt.mkdir()
    s.gt_reconstruction.write_text(str(gt))
    return s, gt


def only_camera(result):
    (cam,) = result.reconstruction.cameras.values()
    return cam


# --------------------------------------------------------------------------- refine_intrinsics
def test_refine_none_keeps_the_given_camera_exactly(scene, tmp_path):
    s, _ = scene
    before = sha(s.database)
    cfg = MappingConfig(camera_model="PINHOLE", camera_params=",".join(map(str, GIVEN)), refine_intrinsics="none",
                        num_threads=1)
    res = run_mapping(s.database, s.image_dir, tmp_path / "m", cfg)
    assert res.success and res.num_reg_images == 6
    cam = only_camera(res)
    assert cam.model.name == "PINHOLE"
    np.testing.assert_array_equal(cam.params, GIVEN)  # bit-exact: bundle adjustment never touched them
    assert res.to_dict()["cameras"][0]["params"] == list(GIVEN)
    assert res.refine_intrinsics == "none"
    assert sha(s.database) == before  # written into the mapped copy only


def test_default_is_colmaps_own_behaviour(scene, tmp_path):
    """``default`` sets no flag: same camera as pycolmap's pipeline with its default options
    (focal and distortion refined, principal point fixed)."""
    import pycolmap

    s, _ = scene
    res = run_mapping(s.database, s.image_dir, tmp_path / "m", MappingConfig(refine_intrinsics="default",
                                                                              num_threads=1), seed=2)
    copy = tmp_path / "raw.db"
    shutil.copyfile(s.database, copy)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = opts.mapper.random_seed = opts.triangulation.random_seed = 2
    opts.num_threads = opts.mapper.num_threads = 1
    (tmp_path / "raw").mkdir()
    models = pycolmap.incremental_mapping(str(copy), str(s.image_dir), str(tmp_path / "raw"), opts)
    raw = max(models.values(), key=lambda r: r.num_reg_images())
    (raw_cam,) = raw.cameras.values()
    cam = only_camera(res)
    np.testing.assert_allclose(cam.params, raw_cam.params, rtol=1e-9)
    # what COLMAP does by default: the focal length moves, the principal point does not
    assert cam.params[0] != FOCAL
    assert tuple(cam.params[1:3]) == (WIDTH / 2, HEIGHT / 2)


def test_refine_all_moves_the_principal_point(scene, tmp_path):
    s, _ = scene
    cfg = MappingConfig(camera_model="PINHOLE", camera_params=",".join(map(str, GIVEN)), refine_intrinsics="all",
                        num_threads=1)
    cam = only_camera(run_mapping(s.database, s.image_dir, tmp_path / "m", cfg))
    assert cam.params[2] != GIVEN[2] and cam.params[3] != GIVEN[3]


def test_camera_model_without_params_keeps_the_focal_length(scene, tmp_path):
    s, _ = scene
    cfg = MappingConfig(camera_model="simple_pinhole", refine_intrinsics="none", num_threads=1)
    cam = only_camera(run_mapping(s.database, s.image_dir, tmp_path / "m", cfg))
    assert cam.model.name == "SIMPLE_PINHOLE"
    np.testing.assert_allclose(cam.params, [FOCAL, WIDTH / 2, HEIGHT / 2])


# --------------------------------------------------------------------------- bad parameter lists
@pytest.mark.parametrize("model, params, message", [
    ("PINHOLE", "1,2,3", "PINHOLE takes 4 parameters, got 3"),
    ("PINHOLE", "700,700,320,abc", "'abc' is not a number"),
    ("PINHOLE", "700,700,320,nan", "not a finite number"),
    ("NO_SUCH_MODEL", "1", "unknown camera model 'NO_SUCH_MODEL'"),
])
def test_bad_parameter_lists(model, params, message):
    with pytest.raises(ValueError, match=message):
        parse_camera_params(model, params)
    with pytest.raises(ValueError, match=message):
        MappingConfig(camera_model=model, camera_params=params)


def test_params_need_a_model_and_refine_is_a_closed_choice():
    with pytest.raises(ValueError, match="camera_params needs camera_model"):
        MappingConfig(camera_params="1,2,3,4")
    with pytest.raises(ValueError, match="refine_intrinsics='some' is not one of: all, default, none"):
        MappingConfig(refine_intrinsics="some")
    assert MappingConfig(refine_intrinsics="NONE").refine_intrinsics is RefineIntrinsics.NONE


@pytest.mark.parametrize("extra", [
    ["--camera-model", "PINHOLE", "--camera-params", "1,2,3"],
    ["--camera-model", "PINHOLE", "--camera-params", "1,2,x,4"],
    ["--camera-model", "FISH", "--camera-params", "1,2,3,4"],
    ["--camera-params", "1,2,3,4"],
])
def test_map_cli_rejects_bad_cameras_in_one_line(scene, tmp_path, capsys, extra):
    s, _ = scene
    rc = main(["map", "--database", str(s.database), "--images", str(s.image_dir), "--output", str(tmp_path / "m"),
               "-q", *extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and "camera" in err
    assert not (tmp_path / "m").exists()  # refused before anything ran


def test_map_cli_known_camera(scene, tmp_path):
    s, _ = scene
    out = tmp_path / "m"
    assert main(["map", "--database", str(s.database), "--images", str(s.image_dir), "--output", str(out), "-q",
                 "--camera-model", "PINHOLE", "--camera-params", ",".join(map(str, GIVEN)),
                 "--refine-intrinsics", "none", "--threads", "1", "--json", str(tmp_path / "m.json")]) == 0
    info = json.loads((tmp_path / "m.json").read_text())
    assert info["cameras"][0]["model"] == "PINHOLE" and info["cameras"][0]["params"] == list(GIVEN)


# --------------------------------------------------------------------------- AUC thresholds
def test_auc_below_the_smallest_error_is_zero_and_above_the_largest_close_to_one():
    errors = [0.7, 1.5, 3.0, 4.5, 8.0]
    lo, hi = pm.pose_auc(errors, [0.5, 1000.0])
    assert lo == 0.0
    assert hi > 0.99
    aucs = pm.pose_auc(errors, DEFAULT_AUC_THRESHOLDS_DEG)
    assert all(a <= b for a, b in itertools.pairwise(aucs))  # monotone in the threshold
    # one failure in five caps every AUC at 0.8
    assert max(pm.pose_auc([*errors[:4], math.inf], [1000.0])) <= 0.8


def test_auc_thresholds_keep_5_10_20_and_reject_bad_values():
    assert auc_thresholds() == (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
    assert auc_thresholds([0.25, 1]) == (0.25, 1.0, 5.0, 10.0, 20.0)
    assert [auc_key(t) for t in (0.5, 1.0, 20.0, 0.25)] == ["auc0.5", "auc1", "auc20", "auc0.25"]
    for bad in ([0.0], [-1.0], [math.inf]):
        with pytest.raises(ValueError, match="AUC thresholds must be positive"):
            auc_thresholds(bad)


def test_report_has_every_auc_key_and_model_analyzer_statistics(scene, tmp_path, capsys):
    s, gt = scene
    res = run_mapping(s.database, s.image_dir, tmp_path / "m", MappingConfig(num_threads=1))
    rep = build_report(reconstruction=res.reconstruction, database=s.database, gt=gt)
    for sec in ("model_pose_auc", "two_view_pose_auc_E", "two_view_pose_auc_F"):
        values = [rep[sec][auc_key(t)] for t in DEFAULT_AUC_THRESHOLDS_DEG]
        assert all(a <= b + 1e-12 for a, b in itertools.pairwise(values)), (sec, values)
    stats = rep["reconstruction"]
    for key in ("num_cameras", "num_images", "num_reg_images", "num_points3D", "num_observations",
                "mean_track_length", "mean_observations_per_image", "mean_reprojection_error"):
        assert key in stats
    assert stats["mean_observations_per_image"] == pytest.approx(stats["num_observations"] / stats["num_reg_images"])
    # the CLI: chosen thresholds (plus 5/10/20) in the JSON and the table, a bad one is exit 2
    js = tmp_path / "r.json"
    assert main(["report", "--model", str(res.output), "--gt", str(gt), "--auc-thresholds", "0.25", "3",
                 "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "@0.25" in out and "@3" in out and "@20" in out
    keys = set(json.loads(js.read_text())["model_pose_auc"])
    assert {"auc0.25", "auc3", "auc5", "auc10", "auc20"} <= keys and "auc0.5" not in keys
    assert main(["report", "--model", str(res.output), "--auc-thresholds", "-1"]) == 2


# --------------------------------------------------------------------------- compare: GT cameras, repeats
def test_compare_repeats_with_gt_cameras(scene, tmp_path, capsys):
    s, gt = scene
    before = sha(s.database)
    out = tmp_path / "cmp"
    rc = main(["compare", "--database", str(s.database), "--images", str(s.image_dir), "--output", str(out),
               "--gt", str(gt), "--workers", "1", "--set", "pipeline.refine_keypoints=false",
               "--set", "mapping.num_threads=1",
               "--camera-from-gt", "--refine-intrinsics", "none", "--repeats", "2", "--seed", "3"])
    assert rc == 0
    assert sha(s.database) == before
    printed = capsys.readouterr().out
    assert "median [min-max] of 2 runs" in printed
    cmp = json.loads((out / "compare.json").read_text())
    (gt_cam,) = s.gt_reconstruction.cameras.values()
    for side in ("baseline", "refined"):
        rpt = cmp[side]["repeats"]
        assert rpt["num_runs"] == 2 and rpt["seeds"] == [3, 4] and len(rpt["runs"]) == 2
        for run in rpt["runs"]:
            # every run kept the GT camera exactly
            assert run["mapping"]["cameras"][0]["params"] == [float(v) for v in gt_cam.params]
            assert run["mapping"]["refine_intrinsics"] == "none"
        regs = [r["reconstruction"]["num_reg_images"] for r in rpt["runs"]]
        assert rpt["median"]["reconstruction"]["num_reg_images"] == float(np.median(regs))
        a05 = [r["model_pose_auc"]["auc0.5"] for r in rpt["runs"]]
        assert rpt["min"]["model_pose_auc"]["auc0.5"] == min(a05)
        assert rpt["max"]["model_pose_auc"]["auc0.5"] == max(a05)
        assert {"auc0.5", "auc1", "auc2", "auc5", "auc10", "auc20"} <= set(rpt["median"]["model_pose_auc"])
    assert (out / "baseline" / "runs" / "seed4" / "model").is_dir()
    rows = {r["metric"] for r in cmp["rows"]}
    assert {"model pose AUC@0.5 (%)", "model pose AUC@1 (%)", "model pose AUC@5 (%)",
            "mean observations per image"} <= rows


def test_compare_camera_from_gt_needs_gt(scene, tmp_path, capsys):
    s, _ = scene
    rc = main(["compare", "--database", str(s.database), "--images", str(s.image_dir), "--output",
               str(tmp_path / "c"), "--camera-from-gt", "-q"])
    assert rc == 2 and "--camera-from-gt needs --gt" in capsys.readouterr().err
    rc = main(["compare", "--database", str(s.database), "--images", str(s.image_dir), "--output",
               str(tmp_path / "c"), "--repeats", "0", "-q"])
    assert rc == 2


def test_a_recipe_file_sets_known_cameras(tmp_path):
    from colmap_miho.recipe import load_recipe

    path = tmp_path / "calibrated.toml"
    path.write_text('[mapping]\ncamera_model = "PINHOLE"\ncamera_params = "700, 701, 320.5, 240.25"\n'
                    'refine_intrinsics = "none"\nnum_threads = 1\n', encoding="utf-8")
    m = load_recipe(str(path)).mapping
    assert m.refine_intrinsics is RefineIntrinsics.NONE
    assert m.intrinsics().params == (700.0, 701.0, 320.5, 240.25) and m.intrinsics().model == "PINHOLE"
    with pytest.raises(ValueError, match=r"\[mapping\] camera_params: camera model PINHOLE takes 4 parameters"):
        load_recipe(str(path), ["mapping.camera_params=1,2"])


def test_run_repeats_needs_compare(scene, tmp_path, capsys):
    s, _ = scene
    rc = main(["run", "--images", str(s.image_dir), "--output", str(tmp_path / "r"), "--repeats", "2", "-q"])
    assert rc == 2 and "--repeats needs --compare" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_bench_known_cameras_table_shows_medians_and_visible_ranges():
    import bench_known_cameras as bk

    assert bk._median_range([0.1, 0.3, 0.2], pct=True) == "20.0 [10.0-30.0]"
    assert bk._median_range([0.12301, 0.12304], pct=True) == "12.3"  # the range would not show
    assert bk._median_range([9, 10, 16], pct=False) == "10 [9-16]"
    runs = [{"num_reg_images": n, "num_images": 16, **{auc_key(t): a for t in bk.AUCS}}
            for n, a in ((16, 0.5), (13, 0.25), (16, 0.75))]
    go = {"outlier_share": 0.125, "correct_pair_outlier_share": 0.05, "num_correct": 700}
    rows = [{"scene": "s", "setting": "default", "row": "ncc", "mapper": "incremental", "runs": runs,
             "gt_outliers": go, "keypoint_accuracy": {"residual_median_px": 0.2, "wrong_track_share": 0.01}},
            {"scene": "s", "setting": "default", "row": "input", "mapper": "incremental", "runs": runs[:1],
             "gt_outliers": go, "keypoint_accuracy": {}},
            {"scene": "s", "setting": "default", "row": "input", "mapper": "global", "runs": runs[:1]}]
    lines = bk.table(rows, "incremental").splitlines()
    assert len(lines) == 4 and lines[2].startswith("| s | default | input | 16/16 | 50.0 |")  # input first
    assert lines[3] == ("| s | default | ncc | 16 [13-16]/16 | 50.0 [25.0-75.0] | 50.0 [25.0-75.0] | "
                        "50.0 [25.0-75.0] | 50.0 [25.0-75.0] | 12.5 | 5.0 | 700 | 0.200 | 1.00 |")
    assert bk.table(rows, "global").splitlines()[-1].endswith("| - | - | - | - | - |")
    assert "**global mapper**" in bk.tables(rows)


def test_bench_known_cameras_json_merges_piecewise_runs(tmp_path):
    import bench_known_cameras as bk

    def row(scene, name, value):
        return {"scene": scene, "setting": "default", "row": name, "mapper": "incremental", "v": value}

    path = tmp_path / "out.json"
    bk.save_json(path, [row("a", "input", 1), row("a", "oracle", 1)], ["--scenes", "a"])
    bk.save_json(path, [row("a", "oracle", 2), row("b", "input", 3)], ["--scenes", "a", "b"])
    data = json.loads(path.read_text())
    assert [(r["scene"], r["row"], r["v"]) for r in data["rows"]] == [("a", "input", 1), ("a", "oracle", 2),
                                                                      ("b", "input", 3)]
    assert data["commands"] == [["--scenes", "a"], ["--scenes", "a", "b"]]


@pytest.mark.parametrize("refine, flags", [
    ("all", (True, True, True)), ("none", (False, False, False)), ("default", None)])
def test_refine_flags_reach_both_mappers(monkeypatch, tmp_path, refine, flags):
    """The pipelines' own options get the flags (incremental: bundle adjustment and image
    registration; global: its bundle adjustment); ``default`` leaves pycolmap's defaults."""
    import pycolmap

    from colmap_miho.sfm.mapping import _run_mapper

    seen = {}
    monkeypatch.setattr(pycolmap, "incremental_mapping", lambda db, im, out, opts, **kw: seen.update(inc=opts) or {})
    monkeypatch.setattr(pycolmap, "global_mapping", lambda db, im, out, opts, **kw: seen.update(glo=opts) or {})
    for mapper in ("incremental", "global"):
        _run_mapper(MappingConfig(mapper=mapper, refine_intrinsics=refine), 0, tmp_path / "db", tmp_path, tmp_path,
                    None)
    inc, ba = seen["inc"], seen["glo"].mapper.bundle_adjustment
    ref_inc, ref_ba = pycolmap.IncrementalPipelineOptions(), pycolmap.GlobalPipelineOptions().mapper.bundle_adjustment
    got_inc = (inc.ba_refine_focal_length, inc.ba_refine_principal_point, inc.ba_refine_extra_params)
    got_ba = (ba.refine_focal_length, ba.refine_principal_point, ba.refine_extra_params)
    if flags is None:
        assert got_inc == (ref_inc.ba_refine_focal_length, ref_inc.ba_refine_principal_point,
                           ref_inc.ba_refine_extra_params)
        assert got_ba == (ref_ba.refine_focal_length, ref_ba.refine_principal_point, ref_ba.refine_extra_params)
        assert inc.mapper.abs_pose_refine_focal_length == ref_inc.mapper.abs_pose_refine_focal_length
    else:
        assert got_inc == flags and got_ba == flags
        got_abs = (inc.mapper.abs_pose_refine_focal_length, inc.mapper.abs_pose_refine_extra_params)
        assert got_abs == (flags[0], flags[2])
