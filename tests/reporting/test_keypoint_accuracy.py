"""Keypoint accuracy under GT geometry: hand-made cameras and tracks with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho import geometry
from colmap_miho.reporting import keypoint_accuracy as ka
from colmap_miho.reporting.demo_scene import look_at
from colmap_miho.reporting.gt_model import CameraPose

# exact keypoints: residual is float64 round-off after Gauss-Newton (measured ~1e-12 px)
EXACT_TOL_PX = 1e-6
# Gaussian noise: median residual within this relative band around sigma * sqrt(2 ln 2) *
# sqrt(1 - 3 / (2 n)) (2-dof Rayleigh shrunk by the 3 dof the triangulated point absorbs)
NOISE_REL_TOL = 0.12
NUM_VIEWS = 6
NUM_POINTS = 400
WIDTH, HEIGHT = 640, 480


def _cameras(n=NUM_VIEWS):
    K = np.array([[500.0, 0, (WIDTH - 1) / 2], [0, 500.0, (HEIGHT - 1) / 2], [0, 0, 1]])
    cams = {}
    for i, a in enumerate(np.linspace(-0.5, 0.5, n)):
        c = np.array([6.0 * np.sin(a), 0.3 * np.cos(3 * a), -6.0 * np.cos(a) + 6.0])
        R, t = look_at(c, np.array([0.0, 0.0, 6.0]), roll_deg=10.0 * a)
        cams[f"im{i}"] = CameraPose(name=f"im{i}", K=K, R=R, t=t, width=WIDTH, height=HEIGHT)
    return cams


def _project(cam, X):
    p = (cam.K @ (cam.R @ X.T + cam.t[:, None])).T
    return p[:, :2] / p[:, 2:3]


def _scene(noise=0.0, seed=0):
    """Every point seen in every view; keypoint order shuffled per image; all pairs matched."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1.5, -1.0, 5.0], [1.5, 1.0, 7.0], size=(NUM_POINTS, 3))
    cams = _cameras()
    kps, perm = {}, {}
    for name, cam in cams.items():
        p = rng.permutation(NUM_POINTS)  # keypoint j of this image sees point p[j]
        perm[name] = np.argsort(p)  # point i -> keypoint perm[i]
        kps[name] = _project(cam, X[p]) + rng.normal(0.0, noise, (NUM_POINTS, 2))
    names = sorted(cams)
    matches = {(a, b): np.column_stack([perm[a], perm[b]]) for i, a in enumerate(names) for b in names[i + 1:]}
    return cams, kps, matches, perm, X


def test_exact_keypoints_give_zero_residual():
    cams, kps, matches, _, _ = _scene()
    r = ka.keypoint_accuracy(cams, kps, matches)
    assert r.num_tracks == NUM_POINTS and r.num_measured_tracks == NUM_POINTS
    assert r.num_measured_observations == NUM_POINTS * NUM_VIEWS
    assert r.num_conflicting_tracks == 0 and r.num_wrong_tracks == 0 and r.wrong_track_share == 0.0
    assert r.residual_p90_px < EXACT_TOL_PX and r.residual_mean_px < EXACT_TOL_PX
    assert r.num_matches == NUM_POINTS * NUM_VIEWS * (NUM_VIEWS - 1) // 2
    assert r.epipolar_median_px < EXACT_TOL_PX and r.epipolar_share_above == 0.0


def test_dlt_alone_is_exact_and_gauss_newton_helps_with_noise():
    cams, kps, matches, _, _ = _scene(noise=0.7, seed=3)
    exact = ka.keypoint_accuracy(cams, _scene(seed=3)[1], matches, gauss_newton_steps=0)
    assert exact.residual_p90_px < EXACT_TOL_PX
    dlt = ka.keypoint_accuracy(cams, kps, matches, gauss_newton_steps=0)
    gn = ka.keypoint_accuracy(cams, kps, matches)
    assert gn.residual_mean_px <= dlt.residual_mean_px


@pytest.mark.parametrize("sigma", [0.3, 1.0])
def test_gaussian_noise_gives_expected_median(sigma):
    cams, kps, matches, _, _ = _scene(noise=sigma, seed=1)
    r = ka.keypoint_accuracy(cams, kps, matches)
    expected = sigma * np.sqrt(2 * np.log(2)) * np.sqrt(1 - 3 / (2 * NUM_VIEWS))
    assert r.residual_median_px == pytest.approx(expected, rel=NOISE_REL_TOL)
    assert r.residual_mean_px > r.residual_median_px * 0.9 and r.residual_p90_px > r.residual_median_px
    assert r.num_wrong_tracks == 0  # 4 px is far above 1 px noise
    # epipolar distance of noisy matches: ~sigma scale, never zero
    assert 0.2 * sigma < r.epipolar_median_px < 2.0 * sigma


def test_injected_wrong_match_makes_a_wrong_track():
    cams, kps, matches, perm, _ = _scene()
    # point 7 is seen in im2 at a keypoint 30 px off: every match of point 7 with im2 uses it
    bad = len(kps["im2"])
    kps["im2"] = np.vstack([kps["im2"], kps["im2"][perm["im2"][7]] + [30.0, 0.0]])
    for (a, b), m in matches.items():
        if "im2" in (a, b):
            col = 0 if a == "im2" else 1
            m[m[:, col] == perm["im2"][7], col] = bad
    r = ka.keypoint_accuracy(cams, kps, matches)
    assert r.num_wrong_tracks == 1 and r.num_measured_tracks == NUM_POINTS - 1
    assert r.wrong_track_share == pytest.approx(1 / NUM_POINTS)
    assert r.residual_p90_px < EXACT_TOL_PX  # the wrong track is not in the residual statistics
    # the 5 matches of the bad keypoint are 30 px off along x: most are far from their epipolar lines
    assert r.epipolar_share_above > 0
    # a larger threshold takes the track in again (overridable by keyword)
    loose = ka.keypoint_accuracy(cams, kps, matches, track_threshold_px=100.0)
    assert loose.num_wrong_tracks == 0 and loose.num_measured_tracks == NUM_POINTS
    # its 6 observations share the 30 px error: their mean over 2400 observations is > 30/2400/2 px
    assert loose.residual_mean_px > 30.0 / (NUM_POINTS * NUM_VIEWS) / 2


def test_two_keypoints_of_one_image_make_a_conflicting_track():
    cams, kps, matches, perm, _ = _scene()
    # one extra match im0:point 3 <-> im1:point 5 joins tracks 3 and 5
    a, b = ("im0", "im1")
    matches[(a, b)] = np.vstack([matches[(a, b)], [perm[a][3], perm[b][5]]])
    r = ka.keypoint_accuracy(cams, kps, matches)
    assert r.num_conflicting_tracks == 1
    assert r.num_tracks == NUM_POINTS - 1
    assert r.num_measured_tracks == NUM_POINTS - 2 and r.num_wrong_tracks == 0


def test_short_tracks_and_images_without_gt_are_not_measured():
    cams, kps, matches, perm, _ = _scene()
    # only 3 GT cameras: every track still has 3 GT views; with 2 GT cameras, none
    three = {k: cams[k] for k in ("im0", "im1", "im2")}
    r3 = ka.keypoint_accuracy(three, kps, matches)
    assert r3.num_measured_tracks == NUM_POINTS and r3.num_measured_observations == 3 * NUM_POINTS
    assert r3.num_matches == 3 * NUM_POINTS
    r2 = ka.keypoint_accuracy({k: cams[k] for k in ("im0", "im1")}, kps, matches)
    assert r2.num_tracks == 0 and np.isnan(r2.residual_median_px) and np.isnan(r2.wrong_track_share)
    assert r2.to_dict()["residual_median_px"] is None
    r4 = ka.keypoint_accuracy(three, kps, matches, min_track_views=4)
    assert r4.num_tracks == 0


def test_epipolar_distance_exact_for_a_hand_made_case():
    # two identical cameras, the second 1 unit to the right: epipolar lines are the rows y = const
    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    cams = {"a": (K, np.eye(3), np.zeros(3)), "b": (K, np.eye(3), np.array([-1.0, 0, 0]))}
    kps = {"a": np.array([[100.0, 50.0], [300.0, 200.0]]), "b": np.array([[80.0, 53.0], [250.0, 200.5]])}
    r = ka.keypoint_accuracy(cams, kps, {("a", "b"): np.array([[0, 0], [1, 1]])})
    d = geometry.symmetric_epipolar_distance(geometry.fundamental_from_poses(K, np.eye(3), np.zeros(3), K, np.eye(3),
                                                                 np.array([-1.0, 0, 0])),
                                       kps["a"], kps["b"])
    assert d == pytest.approx([3.0, 0.5], abs=1e-9)
    assert r.num_matches == 2 and r.epipolar_median_px == pytest.approx(1.75)
    assert r.epipolar_share_above == pytest.approx(0.5)
    assert r.num_tracks == 0  # two views only


def test_point_behind_the_cameras_is_a_wrong_track():
    cams, kps, matches, perm, X = _scene()
    # keypoints of point 0 replaced by the projections of its mirror behind camera im0
    C = cams["im0"].center
    Xb = C - (X[0] - C)
    for name, cam in cams.items():
        p = cam.K @ (cam.R @ Xb + cam.t)
        kps[name][perm[name][0]] = p[:2] / p[2]
    r = ka.keypoint_accuracy(cams, kps, matches)
    assert r.num_wrong_tracks == 1 and r.num_measured_tracks == NUM_POINTS - 1


def test_to_dict_keys_are_stable_and_errors_are_clear():
    cams, kps, matches, _, _ = _scene()
    d = ka.keypoint_accuracy(cams, kps, matches).to_dict()
    assert list(d) == ["num_matches", "epipolar_median_px", "epipolar_share_above", "num_tracks",
                       "num_conflicting_tracks", "num_measured_tracks", "num_measured_observations",
                       "residual_median_px", "residual_mean_px", "residual_p90_px", "num_wrong_tracks",
                       "wrong_track_share", "epipolar_threshold_px", "track_threshold_px", "min_track_views"]
    with pytest.raises(ValueError, match="min_track_views"):
        ka.keypoint_accuracy(cams, kps, matches, min_track_views=1)
    with pytest.raises(ValueError, match="out of range"):
        ka.keypoint_accuracy(cams, kps, {("im0", "im1"): np.array([[0, NUM_POINTS]])})
    with pytest.raises(ValueError, match="no keypoints"):
        ka.keypoint_accuracy(cams, kps, {("im0", "nope"): np.array([[0, 0]])})
    with pytest.raises(ValueError, match="camera needs"):
        ka.keypoint_accuracy({"im0": (np.eye(3), np.eye(3), np.zeros(2))}, kps, matches)


# --------------------------------------------------------------------------- report wiring
# keypoints are stored as float32 in the database: exact positions come back to ~1e-5 px
# (a missing or doubled 0.5 px conversion gives ~0.5 px)
FLOAT32_TOL_PX = 1e-4
# 0.5 px noise, tracks of 3..6 views: median residual 0.5 * 1.177 * sqrt(1 - 3 / (2 n)) is
# 0.42 (n = 3) .. 0.51 (n = 6)
SYN_NOISE_PX = 0.5
SYN_MEDIAN_RANGE = (0.38, 0.58)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    from miho_bench.synthetic import make_synthetic_scene

    root = tmp_path_factory.mktemp("ka")
    out = {}
    for tag, noise in (("exact", 0.0), ("noisy", SYN_NOISE_PX)):
        s = make_synthetic_scene(root / tag, num_images=6, num_points=200, outlier_ratio=0.0, noise_px=noise,
                                 render_images=False, seed=4)
        gt = root / f"{tag}_gt"
        gt.mkdir()
        s.gt_reconstruction.write_text(str(gt))
        out[tag] = (s, gt)
    return out


def test_report_without_model_measures_the_database(synthetic, tmp_path, capsys):
    import json

    from colmap_miho.cli import main

    s, gt = synthetic["noisy"]
    before = s.database.read_bytes()
    js = tmp_path / "r.json"
    assert main(["report", "--gt", str(gt), "--database", str(s.database), "--json", str(js)]) == 0
    assert s.database.read_bytes() == before
    assert "GT track residual" in capsys.readouterr().out
    r = json.loads(js.read_text())
    assert "reconstruction" not in r and "model_pose_auc" not in r and r["model"] is None
    assert r["two_view_pose_auc_E"]["num_pairs"] == 15
    k = r["keypoint_accuracy"]
    assert SYN_MEDIAN_RANGE[0] < k["residual_median_px"] < SYN_MEDIAN_RANGE[1]
    assert k["num_conflicting_tracks"] == 0 and k["num_wrong_tracks"] == 0 and k["num_measured_tracks"] > 100
    # neither a model nor the GT + database pair: a clear error
    assert main(["report", "--database", str(s.database), "-q"]) == 2


def test_report_exact_keypoints_through_the_database(synthetic):
    """Noise-free keypoints through COLMAP's +0.5 px storage come back on the GT geometry."""
    from colmap_miho.reporting import report as rp

    s, gt = synthetic["exact"]
    k = rp.build_report(database=s.database, gt=gt)["keypoint_accuracy"]
    assert k["num_measured_tracks"] > 100 and k["num_wrong_tracks"] == 0
    assert k["residual_p90_px"] < FLOAT32_TOL_PX and k["epipolar_median_px"] < FLOAT32_TOL_PX


# --------------------------------------------------------------------------- the benchmark
def test_bench_variants_and_stats_columns():
    import bench_accuracy as ba

    assert ba.parse_variant("r6:ncc.template_radius=6, recipe=mop_ncc") == ("r6", "mop_ncc", ["ncc.template_radius=6"])
    assert ba.parse_variant("plain") == ("plain", None, [])
    for bad in ("input", ":a=1", "x:novalue"):
        with pytest.raises(ValueError):
            ba.parse_variant(bad)
    stats = ba.numeric_stats({"levels": 4, "seconds": 1.0, "workers": 2, "note": "x", "flag": True,
                              "walk": {"depth": 3}})
    assert stats == {"levels": 4, "walk.depth": 3}
    cams, kps, matches, _, _ = _scene()
    k = ka.keypoint_accuracy(cams, kps, matches).to_dict()
    text = ba.table([{"scene": "s", "setting": "default", "variant": "input", "keypoint_accuracy": k},
                     {"scene": "s", "setting": "default", "variant": "v", "keypoint_accuracy": k,
                      "median_change_pct": 0.0, "keypoints_moved": 5, "refine_seconds": 1.0, "refine_stats": stats}])
    lines = text.splitlines()
    assert lines[0].endswith("| levels | walk.depth |") and len(lines) == 4
    assert lines[3].split("|")[-3].strip() == "4"


@pytest.mark.realdata
@pytest.mark.slow
def test_bench_on_the_temple_input_agrees_with_the_gt(shared_data, tmp_path):
    """SIFT + COLMAP verification on the Middlebury temple: the stored inliers sit close to the
    GT geometry (data README: Sampson error 0.07-0.14 px), so conventions and loaders agree."""
    import json

    import bench_accuracy as ba

    out = tmp_path / "b.json"
    assert ba.main(["--data", str(shared_data), "--work", str(tmp_path), "--scenes", "middlebury_temple_sparse_ring",
                    "--settings", "default", "--variant", "filter:pipeline.refine_keypoints=false", "--workers", "1",
                    "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["variant"] for r in rows] == ["input", "filter"]
    k = rows[0]["keypoint_accuracy"]
    assert k["num_measured_tracks"] > 100 and k["residual_median_px"] < 0.5 and k["epipolar_median_px"] < 0.5
    assert k["wrong_track_share"] < 0.05
    assert rows[1]["keypoints_moved"] == 0
