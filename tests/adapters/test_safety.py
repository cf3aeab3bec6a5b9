"""The user's database is sacred: checks, working copies, atomic replace, backups, kill -9."""

from __future__ import annotations

import hashlib
import os
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import start_at_write

from colmap_miho.adapters.safety import backup_path, check_database_path, check_not_in_use, default_output_path
from colmap_miho.adapters.working_copy import WorkingCopy
from colmap_miho.cli import main
from colmap_miho.errors import DatabaseError, UserError


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith((".tmp", "-wal", "-shm", "-journal")))





def test_check_database_path_never_creates(tmp_path):
    missing = tmp_path / "typo.db"
    with pytest.raises(DatabaseError, match="database not found"):
        check_database_path(missing)
    assert not missing.exists()
    with pytest.raises(DatabaseError, match="not a file"):
        check_database_path(tmp_path)


def test_default_names(tmp_path):
    assert default_output_path(tmp_path / "a.db") == tmp_path / "a.miho.db"
    b = backup_path(tmp_path / "a.db", now=0)
    assert b.parent == tmp_path and b.name.startswith("a.db.") and b.name.endswith(".bak")


def test_working_copy_discards_on_exception(db_copy):
    digest = sha256(db_copy)
    out = db_copy.with_name("out.db")
    with pytest.raises(RuntimeError, match="boom"):
        with WorkingCopy(db_copy, out) as wc:
            assert wc.path.exists() and wc.path.parent == out.parent
            wc.path.write_bytes(b"garbage")
            raise RuntimeError("boom")
    assert sha256(db_copy) == digest
    assert not out.exists()
    assert leftovers(db_copy.parent) == []


def test_working_copy_refuses_existing_output_and_same_file(db_copy):
    out = db_copy.with_name("out.db")
    out.write_bytes(b"x")
    with pytest.raises(UserError, match="exists; pass --overwrite"):
        WorkingCopy(db_copy, out)
    with pytest.raises(UserError, match="use --in-place"):
        WorkingCopy(db_copy, db_copy)
    with WorkingCopy(db_copy, out, overwrite=True) as wc:
        wc.commit()
    assert sha256(out) == sha256(db_copy)


def test_hot_wal_gives_clear_error_and_empty_wal_is_safe(db_copy):
    """A non-empty -wal nobody holds open is a hot journal (data not in the main file):
    refused, naming it and the way out. An empty -wal and a -shm without a lock (what a
    read-only viewer leaves) hold nothing and must not block."""
    wal, shm = Path(str(db_copy) + "-wal"), Path(str(db_copy) + "-shm")
    wal.write_bytes(b"")
    shm.write_bytes(b"\0" * 32768)
    check_not_in_use(db_copy)
    wal.write_bytes(b"x" * 4096)
    with pytest.raises(DatabaseError, match=r"not closed cleanly: scene\.db-wal holds 4096 bytes.*wal_checkpoint"):
        check_not_in_use(db_copy)
    assert main(["refine", "--database", str(db_copy), "--images", str(db_copy.parent), "-q"]) == 2


HOLD_LOCK = """
import sqlite3, sys, time
con = sqlite3.connect(sys.argv[1], isolation_level=None)
con.execute("PRAGMA journal_mode=" + sys.argv[2])
con.execute("BEGIN IMMEDIATE")
print("locked", flush=True)
time.sleep(60)
"""


@pytest.mark.parametrize("journal, message", [
    ("wal", r"in use by another program .*-shm"),  # COLMAP's mode: side files
    ("delete", "locked by another process"),  # no side file: the POSIX lock probe
])
def test_database_locked_by_another_process(db_copy, journal, message):
    """COLMAP's WAL mode shows side files; a rollback-journal writer shows a POSIX lock."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(db_copy), journal],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(DatabaseError, match=message):
            check_not_in_use(db_copy)
        code = main(["refine", "--database", str(db_copy), "--images", str(db_copy.parent), "-q"])
        assert code == 2
    finally:
        proc.kill()
        proc.wait()


def _refine_cmd(db: Path, images: Path, *extra: str) -> list[str]:
    return ["refine", "--database", str(db), "--images", str(images), "--workers", "1",
            "--no-refine", "-q", *extra]


def _kill_at_write(cli_args: list[str], marker: Path) -> None:
    """Run the CLI in a subprocess whose write stage pauses after its first pair (see
    ``pause_at_write.py``) and SIGKILL it there."""
    proc = start_at_write("pause_at_write.py", marker, *cli_args)
    try:
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sigkill_mid_write_leaves_input_identical(db_copy, scene, tmp_path, capfd):
    digest = sha256(db_copy)
    out = db_copy.with_name("out.db")
    _kill_at_write(_refine_cmd(db_copy, scene.image_dir, "--output", str(out)), tmp_path / "marker")
    assert sha256(db_copy) == digest
    assert not out.exists()
    # the killed run's working copy stays behind (nothing can clean up after SIGKILL), but it
    # is a hidden temp file, never the output or the input
    left = leftovers(db_copy.parent)
    assert left and all(name.startswith(".out.db.") for name in left)
    # the next run says so, names it, and leaves it alone (another run might own it)
    from colmap_miho.adapters.working_copy import leftover_copies

    copies = [name for name in left if name.endswith(".tmp")]  # the rest: its -wal, -shm
    assert len(copies) == 1 and [f.name for f in leftover_copies(out)] == copies
    # the killed run's finished work stays too: a plain rerun refuses, naming both ways out
    capfd.readouterr()
    args = ["refine", "--database", str(db_copy), "--images", str(scene.image_dir),
            "--output", str(out), "--workers", "1", "--no-refine", "-q"]
    assert main(args) == 2
    err = capfd.readouterr().err
    assert "--resume" in err and "--restart" in err and not out.exists()
    assert main([*args, "--resume"]) == 0
    err = capfd.readouterr().err
    assert copies[0] in err and "interrupted" in err
    assert sha256(db_copy) == digest and out.exists()
    assert leftovers(db_copy.parent) == left  # the resumed run removed its store, not the copy


def test_sigkill_in_place_keeps_input_and_backup(db_copy, scene, tmp_path):
    digest = sha256(db_copy)
    _kill_at_write(_refine_cmd(db_copy, scene.image_dir, "--in-place"), tmp_path / "marker")
    assert sha256(db_copy) == digest
    backups = list(db_copy.parent.glob("scene.db.*.bak"))
    assert len(backups) == 1 and sha256(backups[0]) == digest


def test_normal_and_failing_runs_leave_input_identical(db_copy, scene):
    digest = sha256(db_copy)
    out = db_copy.with_name("out.db")
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir),
                 "--output", str(out), "--workers", "1", "--no-refine", "-q"]) == 0
    assert sha256(db_copy) == digest and out.exists()
    assert leftovers(db_copy.parent) == []
    # a failing run (image folder without the images, --strict) cleans up its working copy
    empty = db_copy.parent / "no_images"
    empty.mkdir()
    out2 = db_copy.with_name("out2.db")
    assert main(["refine", "--database", str(db_copy), "--images", str(empty), "--output",
                 str(out2), "--strict", "--workers", "1", "-q"]) == 2
    assert sha256(db_copy) == digest and not out2.exists()
    assert leftovers(db_copy.parent) == []
    # existing output without --overwrite: refused, output untouched
    out_digest = sha256(out)
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir),
                 "--output", str(out), "-q"]) == 2
    assert sha256(out) == out_digest


def test_in_place_writes_backup_and_valid_result(db_copy, scene):
    os.chmod(db_copy, 0o640)
    digest = sha256(db_copy)
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir),
                 "--in-place", "--workers", "1", "--no-refine", "-q"]) == 0
    backups = list(db_copy.parent.glob("scene.db.*.bak"))
    assert len(backups) == 1 and sha256(backups[0]) == digest
    assert sha256(db_copy) != digest
    assert db_copy.stat().st_mode & 0o777 == 0o640  # permissions kept, not mkstemp's 0600
    con = sqlite3.connect(db_copy)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        n = con.execute("SELECT COUNT(*) FROM two_view_geometries").fetchone()[0]
    finally:
        con.close()
    assert n > 0
    assert leftovers(db_copy.parent) == []
