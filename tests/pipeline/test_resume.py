"""``refine --resume``: a run SIGKILLed after some filter chunks continues from them and
writes the same database as an uninterrupted run; finished work is never thrown away
silently, and a resume with other options is one clear error."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import pytest
from helpers import HELPERS, REPO
from helpers.db_contents import assert_same_database
from helpers.small_budget import SMALL_WORKER_MATCHES, two_images

from colmap_miho.cli import main
from colmap_miho.pipeline import track_groups
from colmap_miho.pipeline.store import store_folder
from colmap_miho.pipeline_config import PipelineConfig
from miho_bench.synthetic import make_synthetic_scene

#: Seconds the killed run may take (imports, copy, a few pairs).
KILLED_RUN_TIMEOUT_S = 180


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("resume"), num_images=4, num_points=80,
                                outlier_ratio=0.15, noise_px=1.0, seed=5)


def _args(scene, out, *extra):
    return ["refine", "--database", str(scene.database), "--images", str(scene.image_dir),
            "--output", str(out), "--workers", "1", "--device", "cpu", "-q", *extra]


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "ref.db"
    assert main(_args(scene, out)) == 0
    return out


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _killed_run(scene, out, kind: str, n: int) -> None:
    """Run refine in a subprocess that SIGKILLs itself after ``n`` stored ``kind`` items."""
    cmd = [sys.executable, str(HELPERS / "kill_after_saves.py"), kind, str(n), *_args(scene, out)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=KILLED_RUN_TIMEOUT_S)
    assert proc.returncode == -9, proc.stderr  # killed, not finished
    assert not out.exists()


def _stored(out, prefix):
    return sorted(p.name for p in store_folder(out).glob(f"{prefix}-*.npz"))


def test_killed_run_resumes_to_the_uninterrupted_result(scene, reference, tmp_path, capsys):
    before = _sha(scene.database)
    out = tmp_path / "out.db"
    _killed_run(scene, out, "filter", 2)
    assert _stored(out, "filter") == ["filter-000000.npz", "filter-000001.npz"]
    assert _sha(scene.database) == before  # the input is never written
    capsys.readouterr()

    # without --resume the finished work is not thrown away: one line naming both options
    assert main(_args(scene, out)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--resume" in err[0] and "--restart" in err[0] and str(store_folder(out)) in err[0]
    assert _stored(out, "filter") and not out.exists()

    # a resume with another seed or recipe value is refused, naming what changed
    assert main(_args(scene, out, "--resume", "--seed", "3")) == 2
    assert "another seed" in capsys.readouterr().err
    assert main(_args(scene, out, "--resume", "--set", "filter.t_l=12")) == 2
    err = capsys.readouterr().err
    assert "recipe value filter.t_l" in err and "--restart" in err
    assert len(_stored(out, "filter")) == 2

    js = tmp_path / "s.json"
    assert main(_args(scene, out, "--resume", "--json", str(js))) == 0
    summary = json.loads(js.read_text())
    assert summary["resumed"] and summary["filter_chunks_resumed"] == 2 and summary["pairs_resumed"] == 2
    # the 4 pairs left form one default chunk (the resumed run is not the test runner)
    assert summary["filter_chunks"] == 3 and summary["pairs_filtered"] == 6
    assert summary["runner"] == "inline" and summary["memory_budget_mb"] == 2048
    assert_same_database(reference, out)
    assert not store_folder(out).exists()  # removed after the commit
    assert _sha(scene.database) == before


def test_run_killed_while_refining_resumes_its_groups(scene, reference, tmp_path, monkeypatch):
    out = tmp_path / "out.db"
    _killed_run(scene, out, "group", 1)
    assert len(_stored(out, "filter")) == 6 and _stored(out, "group") == ["group-000000.npz"]
    monkeypatch.setattr(PipelineConfig, "image_budget_bytes", two_images)  # the killed run's groups
    monkeypatch.setattr(track_groups, "MIN_MATCHES_PER_REFINE_WORKER", SMALL_WORKER_MATCHES)
    monkeypatch.setattr(track_groups, "MIN_MATCHES_TO_START_WORKERS", 0)
    js = tmp_path / "s.json"
    assert main(_args(scene, out, "--resume", "--json", str(js))) == 0
    summary = json.loads(js.read_text())
    assert summary["filter_chunks_resumed"] == 6 and summary["refine_groups_resumed"] == 1
    assert summary["refine_groups"] >= 2
    assert_same_database(reference, out)  # reference: default budget, one group


def test_resume_with_another_image_budget_walks_the_groups_again(scene, reference, tmp_path):
    out = tmp_path / "out.db"
    _killed_run(scene, out, "group", 1)
    js = tmp_path / "s.json"
    assert main(_args(scene, out, "--resume", "--json", str(js))) == 0  # default budget: one group
    summary = json.loads(js.read_text())
    assert summary["filter_chunks_resumed"] == 6 and summary["refine_groups_resumed"] == 0
    assert_same_database(reference, out)


def test_restart_discards_the_finished_work(scene, reference, tmp_path):
    out = tmp_path / "out.db"
    _killed_run(scene, out, "filter", 1)
    assert len(_stored(out, "filter")) == 1
    js = tmp_path / "s.json"
    assert main(_args(scene, out, "--restart", "--json", str(js))) == 0
    summary = json.loads(js.read_text())
    assert not summary["resumed"] and summary["filter_chunks_resumed"] == 0
    assert_same_database(reference, out)
    assert not store_folder(out).exists()


def test_resume_without_finished_work_runs_from_the_start(scene, reference, tmp_path):
    out = tmp_path / "out.db"
    assert main(_args(scene, out, "--resume")) == 0
    assert_same_database(reference, out)


def test_failed_run_keeps_its_work_and_says_how_to_resume(scene, reference, tmp_path, monkeypatch, capsys):
    from colmap_miho.pipeline import refine_keypoints as refine_module

    def broken(*args, **kwargs):
        raise RuntimeError("refine stage broke")

    monkeypatch.setattr(refine_module, "walk_groups", broken)
    out = tmp_path / "out.db"
    assert main(_args(scene, out)) == 1
    err = capsys.readouterr().err
    assert "refine stage broke" in err and "--resume" in err and str(store_folder(out)) in err
    assert len(_stored(out, "filter")) == 1
    monkeypatch.undo()
    assert main(_args(scene, out, "--resume")) == 0
    assert_same_database(reference, out)


def test_resume_and_restart_are_exclusive(scene, tmp_path):
    with pytest.raises(SystemExit):
        main(_args(scene, tmp_path / "o.db", "--resume", "--restart"))


def _failed_run(scene, db, out, monkeypatch) -> None:
    """A run that fails in the refine stage, leaving its filter chunk in the store."""
    from colmap_miho.pipeline import refine_keypoints as refine_module

    def broken(*args, **kwargs):
        raise RuntimeError("refine stage broke")

    monkeypatch.setattr(refine_module, "walk_groups", broken)
    args = _args(scene, out)
    args[args.index("--database") + 1] = str(db)
    assert main(args) == 1
    monkeypatch.undo()


def _own_db(scene, tmp_path):
    db = tmp_path / "in.db"
    db.write_bytes(scene.database.read_bytes())
    return db


@pytest.mark.parametrize("damage", ["truncated_chunk", "random_chunk", "random_manifest", "manifest_list",
                                    "manifest_fingerprint_int", "forged_chunk_ids", "forged_chunk_offsets"])
def test_a_damaged_store_names_its_file_and_says_restart(damage, scene, tmp_path, monkeypatch, capsys):
    import os

    db, out = _own_db(scene, tmp_path), tmp_path / "out.db"
    _failed_run(scene, db, out, monkeypatch)
    folder = store_folder(out)
    chunk = folder / _stored(out, "filter")[0]
    target = folder / "manifest.json" if "manifest" in damage else chunk
    if damage == "truncated_chunk":
        target.write_bytes(target.read_bytes()[: target.stat().st_size // 2])
    elif damage == "manifest_list":
        target.write_text("[1, 2]")
    elif damage == "manifest_fingerprint_int":
        target.write_text(json.dumps({**json.loads(target.read_text()), "fingerprint": 1}))
    elif damage.startswith("forged_chunk"):  # still tied to the run (its run_id and file name)
        import numpy as np

        with np.load(target) as z:
            arrays = {k: z[k] for k in z.files}
        if damage == "forged_chunk_ids":
            arrays["pairs"] = arrays["pairs"] + 10**12
        else:
            arrays["offsets"] = arrays["offsets"][::-1].copy()
        np.savez(target, **arrays)
    else:
        target.write_bytes(os.urandom(300))
    capsys.readouterr()
    args = _args(scene, out, "--resume")
    args[args.index("--database") + 1] = str(db)
    assert main(args) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and str(target) in lines[0] and "--restart" in lines[0], lines
    assert "--resume to continue" not in lines[0]
    args[args.index("--resume")] = "--restart"
    assert main(args) == 0


def test_resume_sees_a_database_changed_with_its_size_and_time_kept(scene, tmp_path, monkeypatch, capsys):
    """``cp -p`` of another database keeps size and modification time: the content decides."""
    import os
    import sqlite3

    db, out = _own_db(scene, tmp_path), tmp_path / "out.db"
    _failed_run(scene, db, out, monkeypatch)
    st = db.stat()
    con = sqlite3.connect(db)
    con.execute("UPDATE cameras SET params = params WHERE 0")  # nothing
    con.execute("UPDATE images SET name = name || '' WHERE 1")
    row = con.execute("SELECT image_id, data FROM keypoints LIMIT 1").fetchone()
    data = bytearray(row[1])
    data[0] ^= 0x01
    con.execute("UPDATE keypoints SET data = ? WHERE image_id = ?", (bytes(data), row[0]))
    con.commit()
    con.close()
    os.utime(db, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert db.stat().st_size == st.st_size and db.stat().st_mtime_ns == st.st_mtime_ns
    capsys.readouterr()
    args = _args(scene, out, "--resume")
    args[args.index("--database") + 1] = str(db)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "input database (its content changed since)" in err and "--restart" in err
