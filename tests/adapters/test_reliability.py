"""No path, race, signal or full disk may cost a user their database.

Each test is one case of the misuse attack: the command must exit 1 or 2 with one line naming
the user's file, and the database must stay byte-identical.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import REPO, start_at_write

from colmap_miho.adapters.paths import check_distinct, same_file
from colmap_miho.adapters.working_copy import WorkingCopy
from colmap_miho.cli import main
from colmap_miho.errors import DatabaseError, UserError


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def hidden_leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir()
                  if p.name.endswith((".tmp", "-wal", "-shm", "-journal", ".bak")))


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


@pytest.fixture
def db(db_copy):
    """A private copy of the scene database (``db_copy`` of the adapters' conftest)."""
    return db_copy


def _refine(db: Path, images: Path, *extra: str) -> list[str]:
    return ["refine", "--database", str(db), "--images", str(images), "--workers", "1", "--no-refine",
            "-q", *extra]


# ------------------------------------------------------------------ 1. overlapping paths
def test_check_distinct_follows_symlinks_and_hard_links(tmp_path):
    real = tmp_path / "x.db"
    real.write_bytes(b"data")
    link = tmp_path / "link.db"
    link.symlink_to(real)
    hard = tmp_path / "hard.db"
    os.link(real, hard)
    assert same_file(link, real) and same_file(hard, real) and same_file(tmp_path / "." / "x.db", real)
    for out in (real, link, hard, tmp_path / "sub" / ".." / "x.db"):
        with pytest.raises(UserError, match=r"--json .* is the same file as --database .*choose another"):
            check_distinct({"--database": real}, {"--json": out})
    with pytest.raises(UserError, match="SQLite's -wal file"):
        check_distinct({"--database": real}, {"--json": Path(str(real) + "-wal")})
    with pytest.raises(UserError, match="--features and --matches are the same file.*choose another --matches"):
        check_distinct({}, {"--features": tmp_path / "f.h5", "--matches": tmp_path / "f.h5"})
    check_distinct({"--database": real, "--images": None}, {"--json": tmp_path / "summary.json", "--ply": None})


@pytest.mark.parametrize("case", ["refine_json_is_database", "refine_json_is_output",
                                  "refine_json_is_default_output", "refine_in_place_json_link",
                                  "map_json", "report_json", "export_features", "export_matches"])
def test_overlapping_output_is_refused_before_work(case, db, scene, tmp_path, capfd):
    """Every command that would write where it reads exits 2 with one line; nothing changes."""
    digest = sha256(db)
    link = tmp_path / "alias.json"
    link.symlink_to(db)
    out = db.with_name("out.db")
    argv = {
        "refine_json_is_database": _refine(db, scene.image_dir, "--json", str(db)),
        "refine_json_is_output": _refine(db, scene.image_dir, "--output", str(out), "--json", str(out)),
        "refine_json_is_default_output": _refine(db, scene.image_dir, "--json", str(db.with_name("scene.miho.db"))),
        "refine_in_place_json_link": _refine(db, scene.image_dir, "--in-place", "--json", str(link)),
        "map_json": ["map", "--database", str(db), "--images", str(scene.image_dir), "--output",
                     str(tmp_path / "model"), "--json", str(db), "-q"],
        "report_json": ["report", "--database", str(db), "--gt", str(tmp_path), "--json", str(db), "-q"],
        "export_features": ["export", "--database", str(db), "--features", str(db), "--matches",
                            str(tmp_path / "m.h5"), "--overwrite", "-q"],
        "export_matches": ["export", "--database", str(link), "--features", str(tmp_path / "f.h5"),
                           "--matches", str(db), "--overwrite", "-q"],
    }[case]
    capfd.readouterr()
    assert main(argv) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "same file" in lines[0] and "choose another" in lines[0], lines
    assert sha256(db) == digest
    assert not out.exists() and not (tmp_path / "model").exists()
    assert hidden_leftovers(db.parent) == []


# ------------------------------------------------------------------ 2. side files before the replace
def test_bad_json_path_fails_before_the_in_place_replace(db, scene, capfd):
    digest = sha256(db)
    bad = db.parent / "no_such_folder" / "summary.json"
    assert main(_refine(db, scene.image_dir, "--in-place", "--json", str(bad))) == 2
    assert "--json folder does not exist" in capfd.readouterr().err
    assert sha256(db) == digest
    assert hidden_leftovers(db.parent) == []  # no backup either: nothing was replaced


def test_json_is_written_with_the_commit(db, scene, tmp_path):
    summary = tmp_path / "summary.json"
    out = db.with_name("out.db")
    assert main(_refine(db, scene.image_dir, "--output", str(out), "--json", str(summary))) == 0
    data = json.loads(summary.read_text())
    assert data["output"] == str(out) and out.exists()
    assert hidden_leftovers(tmp_path) == [] and hidden_leftovers(db.parent) == []


def test_side_file_staging_failure_replaces_nothing(db, tmp_path):
    """A side file that cannot be written fails inside the block: the output is not created."""
    out = db.with_name("out.db")
    with pytest.raises(UserError, match="cannot write .*nothing was replaced"):
        with WorkingCopy(db, out) as wc:
            wc.stage_side_file(tmp_path / "missing" / "s.json", "{}")
            wc.commit()
    assert not out.exists() and hidden_leftovers(db.parent) == []


# ------------------------------------------------------------------ 3. in place on a symlink
def test_in_place_on_a_symlink_refines_the_target_and_keeps_the_link(db, scene, tmp_path):
    digest = sha256(db)
    link_dir = tmp_path / "links"
    link_dir.mkdir()
    link = link_dir / "project.db"
    link.symlink_to(db)
    assert main(_refine(link, scene.image_dir, "--in-place")) == 0
    assert link.is_symlink() and link.resolve() == db.resolve()
    assert sha256(db) != digest  # the real database was refined
    backups = list(db.parent.glob("scene.db.*.bak"))  # beside the real file
    assert len(backups) == 1 and sha256(backups[0]) == digest
    assert list(link_dir.iterdir()) == [link]


# ------------------------------------------------------------------ 4. checks repeated at commit time
def test_output_created_during_the_run_is_not_replaced(db):
    out = db.with_name("out.db")
    with pytest.raises(UserError, match="created by another program during the run.*--overwrite"):
        with WorkingCopy(db, out) as wc:
            out.write_bytes(b"the other run's result")
            wc.commit()
    assert out.read_bytes() == b"the other run's result"
    assert hidden_leftovers(db.parent) == []


HOLD_OPEN = """
import sqlite3, sys, time
con = sqlite3.connect(sys.argv[1], isolation_level=None)
con.execute("PRAGMA journal_mode=wal")
con.execute("SELECT COUNT(*) FROM images").fetchall()
print("open", flush=True)
time.sleep(60)
"""


def test_overwrite_of_an_output_held_open_is_refused_at_commit(db):
    out = db.with_name("out.db")
    out.write_bytes(db.read_bytes())
    digest = sha256(out)
    with WorkingCopy(db, out, overwrite=True) as wc:
        proc = subprocess.Popen([sys.executable, "-c", HOLD_OPEN, str(out)], stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "open"
            with pytest.raises(DatabaseError, match="in use by another program"):
                wc.commit()
        finally:
            proc.kill()
            proc.wait()
    assert sha256(out) == digest
    assert not list(db.parent.glob(".out.db.*.tmp"))


def test_in_place_input_changed_during_the_run_is_not_replaced(db):
    with pytest.raises(DatabaseError, match=r"changed during the run.*kept in .*scene\.miho-.*\.db.*backup"):
        with WorkingCopy(db, in_place=True) as wc:
            con = sqlite3.connect(db)  # another program commits an edit meanwhile
            con.execute("UPDATE cameras SET width = width + 1")
            con.commit()
            con.close()
            edited = sha256(db)
            wc.commit()
    assert sha256(db) == edited  # the other program's edit is still there
    assert len(list(db.parent.glob("scene.miho-*.db"))) == 1
    assert len(list(db.parent.glob("scene.db.*.bak"))) == 1


def test_interrupted_in_place_run_removes_its_backup(db):
    digest = sha256(db)
    with pytest.raises(KeyboardInterrupt):
        with WorkingCopy(db, in_place=True) as wc:
            assert wc.backup is not None and wc.backup.exists()
            raise KeyboardInterrupt
    assert sha256(db) == digest and hidden_leftovers(db.parent) == []


# ------------------------------------------------------------------ 6. signals and orphans
# Seconds orphaned workers may take to notice their parent died (watchdog poll 0.5 s + exit).
ORPHAN_EXIT_S = 30  # an upper bound: a loaded 2-core machine can take over 10 s to schedule the watchdogs

ORPHAN_SCRIPT = """
import os, sys, time
sys.path.insert(0, sys.argv[1])
from colmap_miho.pipeline.workers import process_pool

def work(_):
    time.sleep(120)

if __name__ == "__main__":
    with process_pool(2) as ex:
        futures = [ex.submit(work, k) for k in range(2)]
        while len(ex._processes) < 2:
            time.sleep(0.05)
        time.sleep(1.0)
        print(" ".join(str(p) for p in ex._processes), flush=True)
        time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie awaiting its reaper counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return True


def test_workers_die_with_a_killed_parent(tmp_path):
    import signal
    import time

    script = tmp_path / "orphans.py"
    script.write_text(ORPHAN_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(REPO)], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in proc.stdout.readline().split()]
        children = subprocess.run(["ps", "-o", "pid=", "--ppid", str(proc.pid)], capture_output=True,
                                  text=True).stdout.split()
        pids = sorted({*workers, *map(int, children)})  # the workers and multiprocessing's resource tracker
        assert len(workers) == 2 and len(pids) >= 2 and all(_alive(p) for p in pids)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        deadline = time.monotonic() + ORPHAN_EXIT_S
        while any(_alive(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(p) for p in pids), "workers outlived their parent"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_workers_die_with_a_killed_parent_nobody_has_reaped(tmp_path):
    """A parent killed (SIGKILL: the OOM killer) stays a zombie until whoever started it reaps
    it, and a script reading its output does so only once the pipes close, which the workers
    hold: their watchdogs took the zombie for a live parent, and both waited for ever."""
    import signal
    import time

    script = tmp_path / "orphans.py"
    script.write_text(ORPHAN_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(REPO)], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in proc.stdout.readline().split()]
        assert len(workers) == 2 and all(_alive(p) for p in workers)
        os.kill(proc.pid, signal.SIGKILL)  # not reaped: a zombie while the workers hold its stdout
        deadline = time.monotonic() + ORPHAN_EXIT_S
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(p) for p in workers), "workers outlived their (zombie) parent"
        assert proc.stdout.read() == ""  # the pipe closes: the reader is not held
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


@pytest.mark.parametrize("in_place", [False, True])
def test_sigterm_mid_write_cleans_up_like_ctrl_c(db, scene, tmp_path, in_place):
    import signal

    digest = sha256(db)
    marker = tmp_path / "marker"
    out = db.with_name("out.db")
    args = _refine(db, scene.image_dir, *(["--in-place"] if in_place else ["--output", str(out)]))
    proc = start_at_write("pause_at_write.py", marker, *args)
    try:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143
    lines = error_lines(err)
    assert len(lines) == 1 and lines[0].startswith("ERROR: terminated"), err
    assert "--resume" in lines[0]  # the filtered pairs are kept for a resumed run
    assert sha256(db) == digest and not out.exists()
    assert hidden_leftovers(db.parent) == []  # working copy, its -wal/-shm and the backup removed


# ------------------------------------------------------------------ 5. every command reads safely
CRASH_WITH_WAL = """
import os, sqlite3, sys
con = sqlite3.connect(sys.argv[1], isolation_level=None)
con.execute("PRAGMA journal_mode=wal")
con.execute("PRAGMA wal_autocheckpoint=0")
con.execute("DELETE FROM two_view_geometries")
os._exit(0)  # a crash: the change is only in the -wal, never checkpointed
"""


def _gt_folder(scene, tmp_path: Path) -> Path:
    folder = tmp_path / "gt"
    folder.mkdir()
    scene.gt_reconstruction.write(str(folder))
    return folder


def _hot_wal(db: Path) -> None:
    subprocess.run([sys.executable, "-c", CRASH_WITH_WAL, str(db)], check=True)
    assert Path(str(db) + "-wal").stat().st_size > 0


@pytest.mark.parametrize("command", ["map", "report", "export", "compare", "refine"])
def test_hot_wal_is_never_read_stale(command, db, scene, tmp_path, capfd):
    _hot_wal(db)
    digest = sha256(db)
    argv = {
        "map": ["map", "--database", str(db), "--images", str(scene.image_dir), "--output", str(tmp_path / "m")],
        "report": ["report", "--database", str(db), "--gt", str(_gt_folder(scene, tmp_path))],
        "export": ["export", "--database", str(db), "--features", str(tmp_path / "f.h5"),
                   "--matches", str(tmp_path / "m.h5")],
        "compare": ["compare", "--database", str(db), "--images", str(scene.image_dir),
                    "--output", str(tmp_path / "c")],
        "refine": _refine(db, scene.image_dir),
    }[command]
    capfd.readouterr()
    assert main([*argv, "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "not closed cleanly" in lines[0] and str(db) in lines[0], lines
    assert sha256(db) == digest


def test_empty_wal_of_a_viewer_does_not_block(db, scene):
    Path(str(db) + "-wal").write_bytes(b"")
    Path(str(db) + "-shm").write_bytes(b"\0" * 32768)
    assert main(_refine(db, scene.image_dir, "--output", str(db.with_name("out.db")))) == 0


def test_truncated_database_is_one_line(db, scene, tmp_path, capfd):
    data = db.read_bytes()
    db.write_bytes(data[: len(data) * 3 // 4])
    for argv in (_refine(db, scene.image_dir),
                 ["export", "--database", str(db), "--features", str(tmp_path / "f.h5"),
                  "--matches", str(tmp_path / "m.h5"), "-q"]):
        capfd.readouterr()
        assert main(argv) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and f"database {db} is damaged" in lines[0], lines
    assert hidden_leftovers(db.parent) == []


# ------------------------------------------------------------------ 7. disk full, bad values, broken files
def test_free_space_is_checked_before_copying(db, scene, monkeypatch, capfd):
    import shutil
    from collections import namedtuple

    digest = sha256(db)
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 1000, 1000))
    for extra in ([], ["--in-place"]):
        capfd.readouterr()
        assert main(_refine(db, scene.image_dir, *extra)) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and "not enough free space in" in lines[0], lines
    assert sha256(db) == digest and hidden_leftovers(db.parent) == []


@pytest.mark.parametrize("in_place", [False, True])
def test_disk_full_while_copying_leaves_nothing_behind(db, scene, monkeypatch, capfd, in_place):
    """A patched copy writes half the file, then fails with ENOSPC (a real full disk needs a
    small tmpfs, which tests cannot mount): one line, no truncated backup or working copy."""
    import errno
    import shutil

    digest = sha256(db)

    def full_disk_copy(fsrc, fdst, *args):
        data = fsrc.read()
        fdst.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(shutil, "copyfileobj", full_disk_copy)
    capfd.readouterr()
    assert main(_refine(db, scene.image_dir, *(["--in-place"] if in_place else []))) == 1  # the full-disk line
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"disk full in {db.parent}" in lines[0] and f"while copying {db}" in lines[0], lines
    assert sha256(db) == digest and hidden_leftovers(db.parent) == []
    assert sorted(p.name for p in db.parent.iterdir()) == ["scene.db"]


@pytest.mark.parametrize("setting, message", [
    ("ncc.template_radius=1000", "template_radius must be in \\[1, 64\\]"),
    ("ncc.search_radius=100000", "search_radius must be in \\[1, 64\\]"),
    ("filter.t_l=inf", "t_l must be a finite number"),
    ("match_check.false_reject=nan", "false_reject must be a finite number"),
    ("ncc.min_ncc=nan", "min_ncc must be a finite number"),
    ("ncc.batch_size=100000000", "batch_size must be in \\[1, 65536\\]"),
    ("filter.t_l=1e308", "t_l must be in \\[0.001, 100000\\]"),
    ("filter.t_l=1e-300", "t_l must be in \\[0.001, 100000\\]"),
    ("filter.t_h=1e-300", "t_h must be in \\[0.001, 100000\\]"),
    ("filter.max_iters=100000000", "max_iters must be in \\[1, 1000000\\]"),
    ("rectify.neighbours=100000", "neighbours must be in \\[6, 1024\\]"),
])
def test_unsafe_settings_are_one_line(setting, message, db, scene, capfd):
    capfd.readouterr()
    assert main(_refine(db, scene.image_dir, "--set", setting)) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1, lines
    import re

    assert re.search(message, lines[0]), lines


def test_match_index_past_the_keypoint_count_is_one_line(db, scene, capfd):
    import numpy as np

    con = sqlite3.connect(db)
    pair_id, rows, data = con.execute(
        "SELECT pair_id, rows, data FROM two_view_geometries WHERE rows > 20 LIMIT 1").fetchone()
    m = np.frombuffer(data, np.uint32).reshape(rows, 2).copy()
    m[3, 1] = 99999
    con.execute("UPDATE two_view_geometries SET data = ? WHERE pair_id = ?", (m.tobytes(), pair_id))
    con.commit()
    con.close()
    digest = sha256(db)
    capfd.readouterr()
    assert main(_refine(db, scene.image_dir)) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"database {db}" in lines[0] and "keypoint 99999" in lines[0], lines
    assert sha256(db) == digest and hidden_leftovers(db.parent) == []


def test_import_into_a_missing_folder_is_one_line(tmp_path, capfd):
    capfd.readouterr()
    assert main(["import", "--features", str(tmp_path / "f.h5"), "--matches", str(tmp_path / "m.h5"),
                 "--images", str(tmp_path), "--database", str(tmp_path / "no" / "new.db"), "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--database folder does not exist" in lines[0], lines


def test_truncated_h5_is_one_line(tmp_path, scene, capfd):
    good, matches = tmp_path / "good.h5", tmp_path / "matches.h5"
    assert main(["export", "--database", str(scene.database), "--features", str(good), "--matches",
                 str(matches), "--layout", "dim", "-q"]) == 0
    bad = tmp_path / "features.h5"
    data = good.read_bytes()
    bad.write_bytes(data[: len(data) * 6 // 10])  # a copy cut short
    capfd.readouterr()
    code = main(["import", "--features", str(bad), "--matches", str(matches), "--images", str(scene.image_dir),
                 "--database", str(tmp_path / "new.db"), "-q"])
    assert code == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"{bad}: cannot open the HDF5 file, damaged or truncated" in lines[0], lines
    assert not (tmp_path / "new.db").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder_is_one_line(db, scene, tmp_path, capfd):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        capfd.readouterr()
        assert main(_refine(db, scene.image_dir, "--output", str(ro / "out.db"))) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and "read-only folder" in lines[0], lines
    finally:
        ro.chmod(0o755)


@pytest.mark.parametrize("name", ["images.bin", "points3D.bin"])
def test_truncated_model_file_is_one_line(name, scene, tmp_path, capfd):
    model = tmp_path / "model"
    model.mkdir()
    scene.gt_reconstruction.write(str(model))
    data = (model / name).read_bytes()
    (model / name).write_bytes(data[: len(data) // 2])
    capfd.readouterr()
    assert main(["report", "--model", str(model), "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"COLMAP model file {model / name} is truncated" in lines[0], lines


# ------------------------------------------------------------------ 8. images checked by decoding and size
def _image_copies(scene, folder: Path) -> list[Path]:
    folder.mkdir()
    for p in scene.image_dir.iterdir():
        (folder / p.name).write_bytes(p.read_bytes())
    return sorted(folder.iterdir())


@pytest.mark.parametrize("damage", ["truncated", "resized"])
def test_bad_image_is_skipped_and_named_or_refused_with_strict(damage, db, scene, tmp_path, capfd):
    import cv2
    import numpy as np

    files = _image_copies(scene, tmp_path / "imgs")
    bad = files[0]
    if damage == "truncated":
        data = bad.read_bytes()
        bad.write_bytes(data[: len(data) * 2 // 3])
        why = "truncated"
    else:
        img = cv2.imread(str(bad))
        cv2.imwrite(str(bad), np.pad(img, ((0, 8), (0, 8), (0, 0))))
        why = "but its camera in the database is"
    summary = tmp_path / "s.json"
    out = tmp_path / "o.db"
    argv = ["refine", "--database", str(db), "--images", str(bad.parent), "--workers", "1", "-q"]
    capfd.readouterr()
    assert main([*argv, "--output", str(out), "--json", str(summary)]) == 0
    err = capfd.readouterr().err
    assert bad.name in err and why in err
    data = json.loads(summary.read_text())
    assert data["images_missing"] == [bad.name]
    assert data["refine_stats"].get("missing_images", 1) == 1  # one count everywhere
    capfd.readouterr()
    assert main([*argv, "--output", str(tmp_path / "o2.db"), "--strict"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert [line for line in lines if line.startswith("ERROR")] == lines[-1:]
    assert str(bad) in lines[-1] and why in lines[-1] and "--strict" in lines[-1]
    assert not (tmp_path / "o2.db").exists()


def test_wrong_image_folder_is_an_error_not_a_silent_success(db, tmp_path, capfd):
    empty = tmp_path / "empty"
    empty.mkdir()
    capfd.readouterr()
    assert main(["refine", "--database", str(db), "--images", str(empty), "--workers", "1", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert lines[-1].startswith("ERROR: none of the 4 images") and "--no-refine" in lines[-1], lines
    assert hidden_leftovers(db.parent) == [] and not db.with_name("scene.miho.db").exists()


# ------------------------------------------------------------------ 4. races, with a real second process
def _run_held(cli_args: list[str], tmp_path: Path, meanwhile) -> tuple[int, str]:
    """Run the CLI in a subprocess held in its write stage, call ``meanwhile()``, let it finish;
    returns its exit code and stderr."""

    marker, resume = tmp_path / "marker", tmp_path / "resume"
    proc = start_at_write("hold_at_write.py", marker, str(resume), *cli_args)
    try:
        meanwhile()
        resume.write_text("go")
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err


def test_two_runs_writing_one_output_the_second_is_refused_at_once(db, scene, tmp_path, capfd):
    out = db.with_name("out.db")

    def other_run_is_refused():
        capfd.readouterr()
        assert main(_refine(db, scene.image_dir, "--output", str(out))) == 2
        err = capfd.readouterr().err
        assert "another colmap-miho run" in err and not out.exists(), err

    code, err = _run_held(_refine(db, scene.image_dir, "--output", str(out)), tmp_path, other_run_is_refused)
    assert code == 0, err
    assert not list(db.parent.glob(".out.db.miho-run"))  # the first run's store went with its commit
    con = sqlite3.connect(out)  # the first result is whole
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    finally:
        con.close()
    assert hidden_leftovers(db.parent) == []


def test_in_place_edit_by_another_program_during_the_run_is_kept(db, scene, tmp_path):
    def other_program_edits():
        con = sqlite3.connect(db)
        con.execute("UPDATE cameras SET width = width + 1")
        con.commit()
        con.close()

    code, err = _run_held(_refine(db, scene.image_dir, "--in-place"), tmp_path, other_program_edits)
    assert code == 2 and "changed during the run" in err, err
    con = sqlite3.connect(db)
    try:
        widths = [w for (w,) in con.execute("SELECT width FROM cameras")]
    finally:
        con.close()
    assert widths and all(w == 641 for w in widths), widths  # the other program's edit survived
    assert len(list(db.parent.glob("scene.miho-*.db"))) == 1  # the work is kept, named
    assert len(list(db.parent.glob("scene.db.*.bak"))) == 1


def test_overwrite_of_an_output_opened_during_the_run_is_refused(db, scene, tmp_path):
    out = db.with_name("out.db")
    out.write_bytes(db.read_bytes())
    digest = sha256(out)
    holder = []

    def viewer_opens_output():
        proc = subprocess.Popen([sys.executable, "-c", HOLD_OPEN, str(out)], stdout=subprocess.PIPE, text=True)
        holder.append(proc)
        assert proc.stdout.readline().strip() == "open"

    try:
        code, err = _run_held(_refine(db, scene.image_dir, "--output", str(out), "--overwrite"), tmp_path,
                              viewer_opens_output)
    finally:
        for proc in holder:
            proc.kill()
            proc.wait()
    assert code == 2 and "in use by another program" in err, err
    assert sha256(out) == digest
    assert not list(db.parent.glob(".out.db.*.tmp"))


def test_disk_full_while_writing_is_one_line(db, scene, monkeypatch, capfd):
    """The write stage fails with ENOSPC (patched: a real full disk needs a small tmpfs): one
    line, exit 1, the input untouched and the working copy removed."""
    import errno

    import colmap_miho.pipeline.write as write_stage

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(write_stage, "write_pair", full)
    digest = sha256(db)
    capfd.readouterr()
    assert main(_refine(db, scene.image_dir, "--in-place")) == 1
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"disk full while writing in {db.parent}; {db} is unchanged" in lines[0], lines
    assert sha256(db) == digest and hidden_leftovers(db.parent) == []


def test_read_only_folders_are_one_line_even_as_root(db, scene, tmp_path, monkeypatch, capfd):
    """Root writes into read-only folders, so the folder is made read-only to ``os.access``
    (the check the commands make before any work) for this test."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == ro else real_access(p, mode, **kw))
    digest = sha256(db)
    for extra, message in ((["--output", str(ro / "out.db")], f"cannot write in {ro} (read-only folder)"),
                           (["--json", str(ro / "s.json")], f"--json {ro / 's.json'}: cannot write in {ro}")):
        capfd.readouterr()
        assert main(_refine(db, scene.image_dir, *extra)) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and message in lines[0], lines
    assert sha256(db) == digest and hidden_leftovers(db.parent) == [] and list(ro.iterdir()) == []


@pytest.mark.parametrize("case", ["map_output_is_a_file", "report_pairs_missing"])
def test_misplaced_paths_are_one_line(case, db, scene, tmp_path, capfd):
    afile = tmp_path / "notes.txt"
    afile.write_text("notes")
    argv, message = {
        "map_output_is_a_file": (["map", "--database", str(db), "--images", str(scene.image_dir), "--output",
                                  str(afile)], f"--output {afile} is a file; give a folder"),
        "report_pairs_missing": (["report", "--database", str(db), "--gt", str(tmp_path), "--pairs",
                                  str(tmp_path / "pairs.txt")], "--pairs not found"),
    }[case]
    capfd.readouterr()
    assert main([*argv, "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and message in lines[0], lines
    assert afile.read_text() == "notes"


@pytest.mark.parametrize("in_place", [False, True])
def test_sigterm_during_a_long_c_call_still_exits_and_cleans_up(db, scene, tmp_path, in_place):
    """Python serves signals between bytecodes only: during a long COLMAP (C++) call the CLI's
    watcher thread removes the working files and exits 143 after the grace period."""
    import signal
    import time

    from colmap_miho.cli import TERM_GRACE_S

    digest = sha256(db)
    marker = tmp_path / "marker"
    out = db.with_name("out.db")
    target = ["--in-place"] if in_place else ["--output", str(out)]
    proc = start_at_write("busy_at_write.py", marker, *_refine(db, scene.image_dir, *target))
    try:
        if in_place:
            assert len(list(db.parent.glob("scene.db.*.bak"))) == 1
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=TERM_GRACE_S + 30)
        waited = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143 and "terminated (SIGTERM) during a COLMAP call" in err, err
    assert "Traceback" not in err and waited < TERM_GRACE_S + 20
    assert sha256(db) == digest and not out.exists() and hidden_leftovers(db.parent) == []
