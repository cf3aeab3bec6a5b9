"""The scale benchmark's measuring functions give the right numbers on tiny inputs."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

pytest.importorskip("psutil")

import bench_scale  # noqa: E402
from bench_scale import (  # noqa: E402
    Scene,
    derived,
    fit_power_law,
    fits,
    fmt,
    measure_refine,
    plot,
    run_measured,
    sift_times,
    table,
)

from colmap_miho.adapters.database import ColmapDatabase  # noqa: E402
from miho_bench.synthetic import make_survey_scene  # noqa: E402

HOLD = "import time, numpy as np; a = np.ones({mb} * 2**20 // 8); time.sleep({s})"


def test_fit_power_law_recovers_the_exponent():
    x = np.array([1e3, 4e3, 2e4, 1e5])
    b, c = fit_power_law(x, 3.0 * x**1.5)
    assert b == pytest.approx(1.5, abs=1e-9) and c == pytest.approx(3.0, rel=1e-9)
    b, _ = fit_power_law(x, 2.0 * x)
    assert b == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="two or more"):
        fit_power_law([5.0, 5.0], [1.0, 2.0])


def test_run_measured_sees_the_child_and_its_workers():
    # one process holding 200 MiB
    one = run_measured([sys.executable, "-c", HOLD.format(mb=200, s=1.0)], poll=0.02)
    assert one.returncode == 0 and one.wall_s >= 1.0
    assert 200 < one.hwm_max_mb < 320 and 200 < one.rss_tree_mb <= one.hwm_sum_mb + 1 < 321
    # a parent and a worker holding 150 MiB each at the same time: the tree sum sees both, the
    # single-process maximum only one; the launching process's own size (this test's, after
    # holding 400 MiB) does not leak into the child's figures as it does into ru_maxrss
    big = np.ones(400 * 2**20 // 8)
    hold = HOLD.format(mb=150, s=1.5)
    code = f"import subprocess, sys; w = subprocess.Popen([sys.executable, '-c', {hold!r}]); {hold}; w.wait()"
    two = run_measured([sys.executable, "-c", code], poll=0.02)
    assert two.returncode == 0
    del big
    assert 300 < two.rss_tree_mb <= two.hwm_sum_mb + 1 < 451
    assert 150 < two.hwm_max_mb < 250
    bad = run_measured([sys.executable, "-c", "import sys; sys.exit(3)"])
    assert bad.returncode == 3
    # CPU seconds: a child that sleeps uses little (its start-up and allocation aside: 2 s of
    # sleep against well under 1 s of importing numpy and touching 1 MiB), one that spins about
    # its wall time
    sleepy = run_measured([sys.executable, "-c", HOLD.format(mb=1, s=2.0)])
    assert sleepy.cpu_s < 0.5 * sleepy.wall_s and sleepy.loadavg >= 0
    busy = "import time; t = time.process_time()\nwhile time.process_time() - t < 0.6: pass"
    spin = run_measured([sys.executable, "-c", busy])
    assert spin.cpu_s >= 0.6


def test_table_and_fits_report_absent_keys_as_na(tmp_path):
    rows = [{"scene": f"survey{n}", "kind": "synthetic", "workers": 2, "matches": m, "refine_s": 0.01 * m,
             "rss_tree_mb": 100 + 0.001 * m, "hwm_max_mb": 90.0, "seconds": {"filter": 1.5}, "levels": 3}
            for n, m in ((25, 1000), (50, 2000), (100, 4000))]
    text = table(rows)
    assert "| survey50 |" in text and "| 1.50 |" in text
    # absent: images, pairs, read, refine, write, hwm_sum, images_loaded, image_decodes,
    # decodes_max, and the
    # four SIFT figures
    assert fmt(None) == "n/a" and text.count("n/a") == 3 * 15
    f = fits(rows)
    assert f["refine_s"]["exponent"] == pytest.approx(1.0, abs=1e-9)
    assert f["hwm_max_mb"]["exponent"] == pytest.approx(0.0, abs=1e-9)
    assert 0 < f["rss_tree_mb"]["exponent"] < 0.1
    assert f["filter"]["exponent"] == pytest.approx(0.0, abs=1e-9)
    assert "refine" not in f  # no stage seconds given
    assert fits(rows[:1]) == {}
    # SIFT on the pair graph only: 10 images = 45 exhaustive pairs of 2 s; refine has 9 pairs
    sift = {"images": 10, "pairs": 9, "refine_s": 6.0, "sift_extract_s": 12.0, "sift_match_s": 90.0}
    assert derived(sift) == {"sift_graph_s": 30.0, "ratio_graph": 0.2}
    assert derived({**sift, "sift_match_s": None}) == {}
    if plot(rows, tmp_path / "scale.png"):
        assert (tmp_path / "scale.png").stat().st_size > 10_000


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_scale")
    sc = make_survey_scene(root, num_images=6, points_per_image=60, width=320, height=240, seed=4)
    return Scene("survey6", "synthetic", sc.database, sc.image_dir, root, info={"pairs": len(sc.pairs)})


def test_measure_refine_reads_the_summary(tiny, monkeypatch):
    with ColmapDatabase(tiny.database) as db:
        pairs, matches = db.num_verified_pairs(), db.num_inlier_matches()
    row = measure_refine(tiny, workers=1, extra=["--no-refine"], poll=0.02, timeout=300)
    summary = json.loads((tiny.work / "refine.json").read_text())
    assert row["images"] == 6 and row["pairs"] == pairs == tiny.info["pairs"] and row["matches"] == matches
    assert row["refine_s"] == summary["seconds"]["total"] > 0
    assert row["child_wall_s"] > row["refine_s"]  # the child also imports and starts
    assert 50 < row["hwm_max_mb"] <= row["hwm_sum_mb"] and 50 < row["rss_tree_mb"] <= row["hwm_sum_mb"] + 1
    assert row["levels"] is None  # --no-refine: no walk
    assert "ratio" not in row  # no SIFT figures given
    # a failing child (no summary written) is an error naming the scene and the child's stderr
    monkeypatch.setattr(bench_scale, "refine_command", lambda *a, **k: [
        sys.executable, "-c", "import sys; sys.exit('error: bad database')"])
    with pytest.raises(RuntimeError, match="refine failed on survey6 .exit 1.: error: bad database"):
        measure_refine(tiny, workers=1, extra=[], poll=0.02, timeout=60)


def test_sift_times_scales_a_sample(tiny):
    full = sift_times(tiny, threads=1, max_features=512)
    assert full["estimated"] is False and full["images_run"] == 6 == full["num_images"]
    assert full["seconds_match"] == full["seconds_match_run"]
    part = sift_times(tiny, threads=1, max_features=512, sample_images=3, seed=1)
    assert part["estimated"] is True and part["images_run"] == 3
    # extraction scaled by 6 / 3 images, matching by 15 / 3 pairs (both rounded to 0.01 s)
    assert part["seconds_extract"] == pytest.approx(2 * part["seconds_extract_run"], abs=0.016)
    assert part["seconds_match"] == pytest.approx(5 * part["seconds_match_run"], abs=0.031)
    assert sift_times(tiny, threads=1, max_features=512, sample_images=3, seed=1) == part  # cached


def test_outcome_counts_the_removed_matches_against_the_ground_truth(tmp_path):
    import shutil

    from miho_bench.calibrated_survey import make_calibrated_survey

    sc = make_calibrated_survey(tmp_path / "s", num_images=8, points_per_image=300, render_images=False, seed=2)
    np.savez(tmp_path / "s" / "point3D_ids.npz", **{str(k): v for k, v in sc.point3D_ids.items()})
    scene = Scene("seq8", "synthetic", sc.database, sc.image_dir, tmp_path / "s", info={"graph": "sequential"})
    same = bench_scale.outcome(scene, sc.database)
    assert same["correct_removed_pct"] == 0 and same["wrong_removed_pct"] == 0
    assert same["correct_in"] > 0 and same["wrong_in"] > 0
    # one pair keeps only its true matches: its wrong ones count as removed, nothing else
    out = tmp_path / "out.db"
    shutil.copy(sc.database, out)
    i, j = sc.pairs[0]
    with ColmapDatabase(out) as db:
        tvg = db.handle.read_two_view_geometry(i, j)
        m = np.asarray(tvg.inlier_matches)
        keep = sc.is_true_match(i, j, m)
        tvg.inlier_matches = np.ascontiguousarray(m[keep])
        db.handle.update_two_view_geometry(i, j, tvg)
    got = bench_scale.outcome(scene, out)
    assert got["correct_out"] == same["correct_in"] and got["wrong_out"] == same["wrong_in"] - (~keep).sum() > 0
    # the wrong matches per pair-size class: the pair's class holds what was removed
    cls = bench_scale.pair_size_class(len(m))
    by = got["wrong_by_pair_size"]
    assert by[cls]["wrong_removed"] == (~keep).sum() and sum(v["wrong_removed"] for v in by.values()) == (~keep).sum()
    assert sum(v["wrong_in"] for v in by.values()) == same["wrong_in"]
    assert sum(v["pairs"] for v in by.values()) == len(sc.pairs)
    assert bench_scale.outcome(Scene("x", "synthetic", sc.database, sc.image_dir, tmp_path), out) == {}


def test_check_table_and_fits_per_graph():
    rows = [{"scene": f"{g[:3]}{n}", "kind": "synthetic", "images": n, "matches": 5000 * n,
             "refine_s": 0.002 * n ** 1.2,
             "seconds": {"filter": 0.01 * n, "match_check": 0.001 * n}, "scene_info": {"graph": g, "loop_pairs": 3},
             "check": {"registered": n, "untrusted": 1, "matches_removed": 7, "pairs_removed": 0, "rounds": 2,
                       "parts_s": {"mapper": 0.5 * n}, "mapper_steps_s": {}},
             "ends_per_image": [9000, 4000, 15000], "correct_removed_pct": 0.5, "wrong_removed_pct": 40.0}
            for g in ("sequential", "retrieval") for n in (100, 200, 400)]
    text = bench_scale.check_table(rows)
    assert "| seq200 | 200 |" in text and "9000 (4000-15000)" in text and "| 199/200 | 2 |" in text
    f = bench_scale.check_fits(rows)
    assert set(f) == {"sequential", "retrieval"}
    assert f["sequential"]["refine_s"] == pytest.approx(1.2, abs=1e-9)
    assert f["retrieval"]["filter"] == pytest.approx(1.0, abs=1e-9)
    assert f["retrieval"]["mapper"] == pytest.approx(1.0, abs=1e-9)
    assert "write" not in f["retrieval"]
    assert bench_scale.check_fits(rows[:1]) == {}


def test_stage_cpu_seconds_places_the_stages_from_the_end():
    # the child ran 10 s; its timer 8 s (2 s of start-up): read 1 s, filter 3 s, check 4 s;
    # the tree used 1 CPU second per second before the check, 2 during it
    series = [(t, t if t <= 6 else 6 + 2 * (t - 6)) for t in np.linspace(0, 10, 101)]
    got = bench_scale.stage_cpu_seconds(series, 10.0, {"read": 1.0, "filter": 3.0, "match_check": 4.0, "total": 8.0})
    assert got == pytest.approx({"read": 1.0, "filter": 3.0, "match_check": 8.0, "total": 12.0})
    assert bench_scale.stage_cpu_seconds(series[:1], 10.0, {"total": 8.0}) == {}
    row = {"stage_cpu_s": got}
    assert bench_scale.check_value(row, "cpu:match_check") == 8.0
    assert bench_scale.check_value(row, "cpu_check_share") == pytest.approx(8 / 12, abs=1e-3)
    assert bench_scale.check_value({}, "cpu_check_share") is None


def test_run_measured_samples_the_tree_cpu():
    busy = "import time; t = time.process_time()\nwhile time.process_time() - t < 0.8: pass"
    run = run_measured([sys.executable, "-c", busy], poll=0.02)
    t, c = np.array(run.cpu_series).T
    assert np.all(np.diff(t) > 0) and np.all(np.diff(c) >= 0)
    assert 0.6 < c[-1] <= run.cpu_s + 0.05  # the last sample misses at most one poll's CPU


def test_pair_size_classes_and_the_outcome_at_the_first_mix():
    assert [bench_scale.pair_size_class(n) for n in (0, 299, 300, 1499, 1500, 10**6)] == [
        "0-299", "0-299", "300-599", "1000-1499", "1500+", "1500+"]
    # the larger survey removes the same share in each class, but holds more of the large pairs
    small = {"0-299": {"pairs": 10, "wrong_in": 100, "wrong_removed": 80},
             "1500+": {"pairs": 10, "wrong_in": 100, "wrong_removed": 20}}
    large = {"0-299": {"pairs": 10, "wrong_in": 100, "wrong_removed": 80},
             "1500+": {"pairs": 30, "wrong_in": 300, "wrong_removed": 60}}
    rows = [{"scene": "seq100", "images": 100, "scene_info": {"graph": "sequential"}, "wrong_removed_pct": 50.0,
             "wrong_by_pair_size": small},
            {"scene": "seq1600", "images": 1600, "scene_info": {"graph": "sequential"}, "wrong_removed_pct": 35.0,
             "wrong_by_pair_size": large}]
    text = bench_scale.pair_size_table(rows)
    assert "| seq1600 | 80.0% (10 / 100) | 20.0% (30 / 300) | 35.00% | 50.0% |" in text
    assert bench_scale.pair_size_table([{"scene": "x"}]) == ""


def test_stage_peaks_take_the_largest_sample_of_each_stage():
    series = [(t, 100.0 + 10 * t) for t in np.linspace(0, 10, 101)]
    got = bench_scale.stage_peaks(series, 10.0, {"read": 1.0, "filter": 3.0, "match_check": 4.0, "total": 8.0})
    assert got == pytest.approx({"read": 130.0, "filter": 160.0, "match_check": 200.0})  # from 2 s: 2-3, 3-6, 6-10
    assert bench_scale.stage_peaks([], 10.0, {"total": 8.0}) == {}
    assert bench_scale.check_value({"client_peak_mb": got}, "mem:filter") == 160.0
