"""The match-check stage inside ``refine``: a pycolmap synthetic scene with planted wrong matches
that are consistent per pair (each joins a point with the point nearest to it one "period"
away, as a repeated facade does): the global estimate exposes them, the output keeps the correct
matches, the report says what was removed, and a resumed run reuses the stored verdicts."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pycolmap
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.pipeline.refine_job import refine_database
from colmap_miho.pipeline.summary import RefineSummary
from colmap_miho.recipe import load_recipe
from colmap_miho.reporting.html_report import match_check_note
from colmap_miho.verification.config import MatchCheckConfig

#: Pixels of keypoint noise.
NOISE_PX = 0.5
#: Matches per pair turned into planted wrong ones.
PLANTED_SHARE = 0.3
#: What the stage must achieve (named tolerances): correct matches removed at most / planted
#: matches left at most (a planted match whose shift runs along its epipolar line stays).
MAX_CORRECT_REMOVED = 0.03
MAX_PLANTED_LEFT = 0.15


@pytest.fixture(scope="module")
def planted_db(tmp_path_factory):
    """(database, image folder, planted matches per pair as a set of (k1, k2))."""
    root = tmp_path_factory.mktemp("planted")
    path = root / "database.db"
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig, o.num_points3D = 1, 1, 8, 400
    o.num_points2D_without_point3D = 0
    rng = np.random.default_rng(0)
    planted: dict[tuple[int, int], set] = {}
    pycolmap.set_random_seed(0)  # pycolmap's one global generator: the scene must not depend on the tests before
    with ColmapDatabase.create(path) as db:
        gt = db.synthesize(o, pycolmap.SyntheticNoiseOptions(point2D_stddev=NOISE_PX))
        pts = {pid: p.xyz for pid, p in gt.points3D.items()}
        ids = np.array(sorted(pts))
        xyz = np.array([pts[i] for i in ids])
        period = np.array([0.0, 0.15, 0.0]) * float(np.ptp(xyz, axis=0).max())
        nearest = {int(ids[k]): int(ids[np.argmin(np.linalg.norm(xyz - (xyz[k] + period), axis=1))])
                   for k in range(len(ids))}
        obs = {int(i): {int(p.point3D_id): k for k, p in enumerate(im.points2D) if p.has_point3D()}
               for i, im in gt.images.items()}
        h = db.handle
        pair_ids, tvgs = h.read_two_view_geometries()
        for pid, tvg in zip(pair_ids, tvgs, strict=True):
            i, j = pycolmap.pair_id_to_image_pair(pid)
            m = np.asarray(tvg.inlier_matches, np.int64)
            inv_i = {k: p for p, k in obs[i].items()}
            rows = [r for r in rng.permutation(len(m))[: int(PLANTED_SHARE * len(m))]
                    if m[r, 0] in inv_i and nearest[inv_i[m[r, 0]]] in obs[j]
                    and nearest[inv_i[m[r, 0]]] != inv_i[m[r, 0]]]
            for r in rows:  # the match goes to the repeated copy instead of the right point
                m[r, 1] = obs[j][nearest[inv_i[m[r, 0]]]]
            planted[(i, j)] = {tuple(m[r].tolist()) for r in rows}
            allm = m.astype(np.uint32)
            h.delete_matches(i, j)
            h.write_matches(i, j, allm)
            tvg.inlier_matches = allm
            h.update_two_view_geometry(i, j, tvg)
    (root / "images").mkdir()
    return path, root / "images", planted


def _output_matches(path):
    with ColmapDatabase(path) as db:
        return {(p.image_id1, p.image_id2): db.matches(p.image_id1, p.image_id2, "verified")
                for p in db.pairs("verified")}


def _run(planted_db, out, *sets, resume=False, restart=False):
    db, images, _ = planted_db
    rec = load_recipe(None, ["pipeline.refine_keypoints=false", "match_check.mode=off", *sets])
    json_path = out.with_suffix(".json")
    refine_database(db, images, out, recipe=rec, workers=1, json_path=json_path, overwrite=True,
                    resume=resume, restart=restart)
    return json.loads(json_path.read_text())


def _shares(planted, matches):
    """(correct matches kept / correct in the input, planted left / planted)."""
    left = sum(len({tuple(r) for r in m.tolist()} & planted.get(p, set())) for p, m in matches.items())
    n_planted = sum(len(s) for s in planted.values())
    correct = sum(len(m) for m in matches.values()) - left
    return correct, left / n_planted


@pytest.mark.slow
def test_planted_matches_are_removed_and_correct_ones_kept(planted_db, tmp_path):
    _, _, planted = planted_db
    off = _run(planted_db, tmp_path / "off.db")
    on = _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    correct_off, left_off = _shares(planted, _output_matches(tmp_path / "off.db"))
    correct_on, left_on = _shares(planted, _output_matches(tmp_path / "on.db"))
    assert left_off > 0.5  # the filter alone keeps most planted matches: they lie on a plane too
    assert left_on <= MAX_PLANTED_LEFT
    assert correct_on >= (1 - MAX_CORRECT_REMOVED) * correct_off
    mc = on["match_check"]
    assert mc["used"] and mc["mode"] == "remove" and not mc["images_untrusted"]
    assert mc["images_registered"] == mc["images"] == 8 and len(mc["images_trusted"]) == 8
    assert mc["matches_removed"] > 0 and 1.0 <= mc["threshold_px"] <= 4.0
    assert mc["mapper_steps"] and "global positioning" in mc["mapper_steps"][0]  # its log's seconds per step
    assert off["match_check"] == {}
    note = match_check_note(mc)  # report.html's sentence
    assert "8 trusted" in note and f"{mc['matches_removed']} of {mc['matches_judged']} judged matches removed" in note
    fields = {f.name for f in dataclasses.fields(RefineSummary)}
    text = RefineSummary(**{k: v for k, v in on.items() if k in fields}).format()  # the CLI summary
    assert "match check: global estimate of 8 of 8 images" in text and "8 trusted" in text


@pytest.mark.slow
def test_flag_mode_removes_nothing(planted_db, tmp_path):
    off = _run(planted_db, tmp_path / "off.db")
    flag = _run(planted_db, tmp_path / "flag.db", "match_check.mode=flag")
    assert flag["match_check"]["used"] and flag["match_check"]["matches_removed"] > 0
    assert flag["matches_kept"] == off["matches_kept"]
    a, b = _output_matches(tmp_path / "off.db"), _output_matches(tmp_path / "flag.db")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_no_estimate_removes_nothing(planted_db, tmp_path, monkeypatch):
    monkeypatch.setattr(pycolmap, "global_mapping", lambda *a, **k: {})
    off = _run(planted_db, tmp_path / "off.db")
    on = _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    assert not on["match_check"]["used"] and "placed 0 images" in on["match_check"]["reason"]
    assert "not used" in match_check_note(on["match_check"])
    a, b = _output_matches(tmp_path / "off.db"), _output_matches(tmp_path / "on.db")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert off["matches_kept"] == on["matches_kept"]


@pytest.mark.slow
def test_resumed_run_reuses_the_stored_verdicts(planted_db, tmp_path, monkeypatch):
    from colmap_miho.pipeline import refine_job as run_module

    ref = _run(planted_db, tmp_path / "ref.db", "match_check.mode=remove")

    def broken(*args, **kwargs):
        raise RuntimeError("write stage broke")

    monkeypatch.setattr(run_module, "run_write", broken)
    out = tmp_path / "out.db"
    with pytest.raises(RuntimeError):
        _run(planted_db, out, "match_check.mode=remove")
    monkeypatch.undo()

    def no_mapper(*args, **kwargs):
        raise AssertionError("the resumed run ran the global mapper again")

    from colmap_miho.sfm import global_estimate

    monkeypatch.setattr(global_estimate, "global_estimate", no_mapper)
    from colmap_miho.pipeline import match_check_stage as stage

    monkeypatch.setattr(stage, "_decide", no_mapper)
    res = _run(planted_db, out, "match_check.mode=remove", resume=True)
    timing = ("seconds", "round_seconds", "mapper_steps", "peak_rss_mb")  # the mapper's time and memory differ
    same = {k: v for k, v in ref["match_check"].items() if k not in timing}
    assert res["resumed"] and {k: v for k, v in res["match_check"].items() if k not in timing} == same
    a, b = _output_matches(tmp_path / "ref.db"), _output_matches(out)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_matches_kept_counts_what_the_check_removed(planted_db, tmp_path):
    on = _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    out = _output_matches(tmp_path / "on.db")
    with ColmapDatabase(planted_db[0]) as db:  # every pair is filtered here: all its matches count
        assert len(db.pairs("verified")) == len(out)
    assert on["match_check"]["matches_removed"] > 0
    assert on["matches_kept"] == sum(len(m) for m in out.values())
    assert on["matches_removed"] == on["matches_in"] - on["matches_kept"]


@pytest.mark.slow
def test_colmap_errors_of_a_failed_estimate_stay_off_the_terminal(planted_db, tmp_path, capfd, monkeypatch):
    monkeypatch.setattr(MatchCheckConfig, "min_pair_matches", 100000)  # no pair enters the estimate
    on = _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    mc = on["match_check"]
    assert not mc["used"] and "Failed to create sparse model" in mc["reason"]  # COLMAP's words, in ours
    err = capfd.readouterr().err
    assert "sparse model" not in err and "sfm.cc" not in err, err


@pytest.mark.slow
def test_the_estimate_leaves_no_temporary_folder(planted_db, tmp_path, monkeypatch):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.setattr("tempfile.tempdir", None)  # gettempdir() reads TMPDIR again
    _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    assert not list(tmp.glob("miho-global-*"))


@pytest.mark.slow
def test_disk_full_in_the_temporary_folder_names_that_folder(planted_db, tmp_path, monkeypatch):
    from colmap_miho.errors import RunFailed

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.setattr("tempfile.tempdir", None)

    def full_disk(*args, **kwargs):
        raise RuntimeError("[database_sqlite.cc:1389] SQLite error: database or disk is full")

    monkeypatch.setattr("colmap_miho.adapters.database.ColmapDatabase.write_scene_copy", full_disk)
    (tmp_path / "out").mkdir()
    with pytest.raises(RunFailed) as err:
        _run(planted_db, tmp_path / "out" / "on.db", "match_check.mode=remove")
    assert str(err.value).startswith(f"disk full in {tmp} ")  # not the output folder


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["cut", "random", "no_meta", "bad_layout"])
def test_a_damaged_verdict_file_is_named_and_resume_refused(planted_db, tmp_path, monkeypatch, damage):
    from colmap_miho.pipeline import refine_job as run_module
    from colmap_miho.pipeline.store import StoreDamaged, store_folder

    out = tmp_path / "out.db"

    def broken(*args, **kwargs):
        raise RuntimeError("write stage broke")

    monkeypatch.setattr(run_module, "run_write", broken)
    with pytest.raises(RuntimeError):
        _run(planted_db, out, "match_check.mode=remove")
    monkeypatch.undo()
    path = store_folder(out) / "stage-match_check.npz"
    data = path.read_bytes()
    if damage == "cut":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "random":
        path.write_bytes(np.random.default_rng(0).bytes(len(data)))
    elif damage == "no_meta":
        np.savez(path, pairs=np.zeros((0, 2), np.int64))
    else:
        np.savez(path, pairs=np.array([[1, 2]]), offsets=np.array([0, 10**6]), failed=np.zeros(3, bool),
                 wrong=np.zeros((0, 2), np.int64), meta=np.array(json.dumps({"mode": "remove"})))
    with pytest.raises(StoreDamaged) as err:
        _run(planted_db, out, "match_check.mode=remove", resume=True)
    assert str(path) in str(err.value) and "--restart" in str(err.value)
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_during_the_global_mapper_stops_the_run_promptly(planted_db, tmp_path, sig):
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from colmap_miho.cli import TERM_GRACE_S

    db, images, _ = planted_db
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    marker, out = tmp_path / "marker", tmp_path / "out.db"
    helper = Path(__file__).resolve().parents[1] / "helpers" / "busy_in_mapper.py"
    proc = subprocess.Popen(
        [sys.executable, str(helper), str(marker), "refine", "--database", str(db), "--images", str(images),
         "--output", str(out), "--workers", "1", "-q", "--no-refine", "--set", "match_check.mode=remove"],
        stderr=subprocess.PIPE, text=True, env={**os.environ, "TMPDIR": str(tmp)})
    try:
        deadline = time.monotonic() + 120
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert marker.exists() and list(tmp.glob("miho-global-*")), "the mapper never started"
        t0 = time.monotonic()
        proc.send_signal(getattr(signal, sig))
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == (130 if sig == "SIGINT" else 143)
    assert took < TERM_GRACE_S + 10
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("ERROR: "), err
    assert not list(tmp.glob("miho-global-*")) and not out.exists()


@pytest.mark.slow
def test_the_default_recipe_checks_matches(planted_db, tmp_path):
    db, images, _ = planted_db
    out = tmp_path / "default.db"
    summary = refine_database(db, images, out, recipe=load_recipe(None, ["pipeline.refine_keypoints=false"]), workers=1)
    assert summary.match_check["mode"] == "remove" and summary.match_check["used"]
    assert summary.match_check["matches_removed"] > 0
    off = refine_database(db, images, tmp_path / "off.db", workers=1,
                          recipe=load_recipe(None, ["pipeline.refine_keypoints=false", "match_check.mode=off"]))
    assert off.match_check == {} and off.matches_kept > summary.matches_kept


@pytest.mark.slow
def test_with_debug_logging_colmaps_log_reaches_the_terminal(planted_db, tmp_path, capfd, caplog, monkeypatch):
    import logging

    caplog.set_level(logging.DEBUG, logger="colmap_miho")  # what -v sets
    monkeypatch.setattr(MatchCheckConfig, "min_pair_matches", 100000)
    _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    assert "Failed to create sparse model" in capfd.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("unfiltered", ["pipeline.min_matches=100000", "filter.min_inliers=100000"])
def test_the_verdicts_on_pairs_written_back_unchanged_reach_the_output(planted_db, tmp_path, unfiltered):
    """Pairs too small to filter and pairs in which the filter found no plane are written back
    unchanged, but the match check judges them: the matches it removes are gone from the output,
    and the summary's matches in -> kept add up to the input and the output."""
    db, _, planted = planted_db
    on = _run(planted_db, tmp_path / "on.db", "match_check.mode=remove", unfiltered)
    out = _output_matches(tmp_path / "on.db")
    with ColmapDatabase(db) as src:
        n_in = sum(p.num_matches for p in src.pairs("verified"))
    assert on["pairs_filtered"] - on["pairs_failed"] == 0
    removed = on["match_check"]["matches_removed"] + on["match_check"]["matches_in_removed_pairs"]
    assert on["match_check"]["matches_removed"] > 0
    assert on["matches_in"] == n_in
    assert on["matches_kept"] == sum(len(m) for m in out.values()) == n_in - removed
    assert on["matches_removed"] == removed
    _, left = _shares(planted, out)
    assert left <= MAX_PLANTED_LEFT


@pytest.mark.slow
def test_image_names_longer_than_a_file_name_do_not_switch_the_check_off(planted_db, tmp_path):
    """The global mapper joins image names to its temporary folder: a name of 300 characters
    made it fail ("File name too long"), and the check was off for the whole scene."""
    import shutil

    db, images, planted = planted_db
    long_db = tmp_path / "long.db"
    shutil.copy(db, long_db)
    with ColmapDatabase(long_db) as d:
        for im in d.handle.read_all_images():
            im.name = f"{'n' * 300}{im.image_id}.jpg"
            d.handle.update_image(im)
    on = _run((long_db, images, planted), tmp_path / "on.db", "match_check.mode=remove")
    assert on["match_check"]["used"], on["match_check"]["reason"]
    assert on["match_check"]["matches_removed"] > 0


def test_a_pair_with_repeated_rows_written_back_unchanged_is_judged(planted_db, tmp_path):
    """A pair too small to filter whose matches repeat a row (counted once, as read): the
    verdicts read back were checked against the row count, so every run (--restart too)
    stopped on "the interrupted run's file stage-match_check.npz is damaged"."""
    import shutil

    db, images, _ = planted_db
    copy = tmp_path / "db.db"
    shutil.copy(db, copy)
    with ColmapDatabase(copy) as cdb:
        h = cdb.handle
        pair_ids, tvgs = h.read_two_view_geometries()
        i, j = pycolmap.pair_id_to_image_pair(pair_ids[0])
        tvg = tvgs[0]
        m = np.asarray(tvg.inlier_matches, np.uint32)
        tvg.inlier_matches = np.concatenate([m, m[:1]])  # its first row twice
        h.update_two_view_geometry(i, j, tvg)
    with ColmapDatabase(copy) as cdb:
        n_in = sum(p.num_matches for p in cdb.pairs("verified"))
        assert len(cdb.matches(i, j, "verified")) == len(m)  # read once
    on = _run((copy, images, None), tmp_path / "on.db", "match_check.mode=remove", "pipeline.min_matches=100000")
    assert on["match_check"]["matches_removed"] > 0 and on["matches_in"] == n_in
    assert on["matches_kept"] == sum(len(x) for x in _output_matches(tmp_path / "on.db").values())


@pytest.mark.slow
def test_correct_matches_the_filter_removed_come_back_and_wrong_ones_do_not(planted_db, tmp_path, monkeypatch):
    """A filter that removes every planted (wrong) match, a third of the correct ones and one
    pair whole: the check gives back most of the correct ones, the emptied pair among them, and
    none of the planted ones, and the summary says so."""
    from colmap_miho.pipeline.records import PairOutcome
    from colmap_miho.pipeline.store import RunStore

    db, _, planted = planted_db
    dropped: dict = {}
    real = RunStore.save_filter_chunk

    def lossy(self, index, pairs, matches, outcomes):
        changed = []
        for p, m, o in zip(pairs, matches, outcomes, strict=True):
            inl = np.array(o.inliers, bool)
            rows = np.flatnonzero(inl)
            bad = np.array([tuple(m[k].tolist()) in planted.get(p, set()) for k in rows], bool)
            good = rows[~bad]
            lose = good if not dropped else good[::3]  # the first pair loses all its correct matches
            dropped[p] = {tuple(m[k].tolist()) for k in lose}
            inl[rows[bad]] = False
            inl[lose] = False
            labels = np.where(inl, o.labels, -1)
            changed.append(PairOutcome(inliers=inl, labels=labels, patch_homographies=o.patch_homographies,
                                       success=o.success))
        return real(self, index, pairs, matches, changed)

    monkeypatch.setattr(RunStore, "save_filter_chunk", lossy)
    on = _run(planted_db, tmp_path / "on.db", "match_check.mode=remove")
    out = _output_matches(tmp_path / "on.db")
    back = sum(len({tuple(r) for r in out.get(p, np.zeros((0, 2))).tolist()} & lost) for p, lost in dropped.items())
    n_dropped = sum(len(s) for s in dropped.values())
    _, left = _shares(planted, out)
    mc = on["match_check"]
    assert left == 0  # nothing wrong comes back
    assert mc["matches_restored"] >= back >= 0.5 * n_dropped  # the filter's own removals may come back too
    assert mc["pairs_revived"] >= 1 and mc["restored_per_pair"]
    assert on["matches_kept"] == sum(len(m) for m in out.values())
    assert f"{mc['matches_restored']} matches the filter removed restored" in match_check_note(mc)


def test_restored_rows_are_kept_again_without_a_homography():
    from colmap_miho.pipeline.records import PairOutcome
    from colmap_miho.pipeline.verdicts import Verdicts

    m = np.arange(12, dtype=np.uint32).reshape(6, 2)
    r = PairOutcome(inliers=np.array([1, 1, 0, 1, 0, 0], bool), labels=np.array([0, 1, -1, 0, -1, -1]),
                    patch_homographies=np.zeros((2, 2, 3, 3)), success=True)
    v = Verdicts(failed={(1, 2): np.array([False, True, False])}, restored={(1, 2): np.array([2, 5])})
    _, out = v.apply({(1, 2): (m, r)})[(1, 2)]
    assert out.inliers.tolist() == [True, False, True, True, False, True]
    assert out.labels.tolist() == [0, -1, -1, 0, -1, -1]
