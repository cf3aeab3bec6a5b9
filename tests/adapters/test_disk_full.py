"""A full disk anywhere is one line naming the disk, the input intact and nothing left filling
it: pycolmap's "database or disk is full" included, and free space checked before the writes
where a native library would abort. Real full disks are small tmpfs mounts (root only)."""

from __future__ import annotations

import contextlib
import hashlib
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from disk import fill, small_disk

from colmap_miho.adapters.staged_write import is_disk_full
from colmap_miho.cli import main


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("ERROR")]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name != "filler")


@contextlib.contextmanager
def db_on_small_disk(db_copy: Path, tmp_path: Path, leave: int) -> Iterator[tuple[Path, Path]]:
    """(disk, database): a copy of ``db_copy`` on a 16 MB file system filled to ``leave``
    free bytes."""
    with small_disk(tmp_path / "mnt", "16m") as disk:
        db = disk / "scene.db"
        shutil.copyfile(db_copy, db)
        fill(disk, leave=leave)
        yield disk, db


def test_sqlite_full_is_recognised():
    import errno
    import sqlite3

    assert is_disk_full(RuntimeError("SQLite error [...]: database or disk is full"))
    assert is_disk_full(sqlite3.OperationalError("database or disk is full"))
    assert is_disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert is_disk_full(OSError("Can't write data (file write failed: errno = 28, error message = "
                                "'No space left on device')"))
    assert not is_disk_full(RuntimeError("Check failed: x"))


def test_pycolmap_disk_full_while_writing_is_one_line(db_copy, scene, monkeypatch, capfd):
    """pycolmap raises ``RuntimeError: ... database or disk is full`` from some writes: a known
    condition (exit 1, one line naming the folder), not "unexpected; report it"."""
    import colmap_miho.pipeline.write as write_stage

    def full(*args, **kwargs):
        raise RuntimeError("[database.cc:123] SQLite error: database or disk is full")

    monkeypatch.setattr(write_stage, "write_pair", full)
    digest = sha256(db_copy)
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1",
                 "--no-refine", "-q"]) == 1
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"disk full while writing in {db_copy.parent}" in lines[0], lines
    assert "unexpected" not in lines[0] and "--resume" in lines[0]  # the filtered pairs are kept
    assert sha256(db_copy) == digest and names(db_copy.parent) == [".scene.miho.db.miho-run", "scene.db"]


def _export(scene, folder: Path) -> tuple[Path, Path]:
    feats, matches = folder / "features.h5", folder / "matches.h5"
    assert main(["export", "--database", str(scene.database), "--features", str(feats), "--matches",
                 str(matches), "-q"]) == 0
    return feats, matches


def test_import_checks_free_space_first(scene, tmp_path, capfd):
    feats, matches = _export(scene, tmp_path)
    with small_disk(tmp_path / "mnt", "1m") as disk:
        fill(disk, leave=64 << 10)
        capfd.readouterr()
        assert main(["import", "--features", str(feats), "--matches", str(matches), "--images",
                     str(scene.image_dir), "--database", str(disk / "new.db"), "-q"]) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and f"not enough free space in {disk}" in lines[0], lines
        assert names(disk) == []


def test_import_fits_a_disk_with_room(scene, tmp_path):
    feats, matches = _export(scene, tmp_path)
    with small_disk(tmp_path / "mnt", "16m") as disk:
        assert main(["import", "--features", str(feats), "--matches", str(matches), "--images",
                     str(scene.image_dir), "--database", str(disk / "new.db"), "-q"]) == 0
        assert names(disk) == ["new.db"]


def test_export_to_a_full_disk_is_one_line_and_leaves_nothing(scene, tmp_path, monkeypatch, capfd):
    """No SIGSEGV from HDF5: free space is checked first; no h5 temporaries, no $TMPDIR copy."""
    tmpdir = tmp_path / "tmpdir"
    tmpdir.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmpdir))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    with small_disk(tmp_path / "mnt", "1m") as disk:
        fill(disk, leave=8 << 10)
        capfd.readouterr()
        assert main(["export", "--database", str(scene.database), "--features", str(disk / "f.h5"), "--matches",
                     str(disk / "m.h5"), "-q"]) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and f"not enough free space in {disk}" in lines[0], lines
        assert names(disk) == [] and list(tmpdir.iterdir()) == []


def test_export_keeps_a_users_partial_files_and_names(scene, tmp_path):
    mine = [tmp_path / ".f.h5.partial", tmp_path / "f.h5.partial", tmp_path / "mine.db.partial"]
    for p in mine:
        p.write_text("mine")
    assert main(["export", "--database", str(scene.database), "--features", str(tmp_path / "f.h5"),
                 "--matches", str(tmp_path / "m.h5"), "-q"]) == 0
    assert all(p.read_text() == "mine" for p in mine)
    assert names(tmp_path) == sorted([".f.h5.partial", "f.h5", "f.h5.partial", "m.h5", "mine.db.partial"])


def test_refine_on_a_disk_too_small_is_refused_up_front(db_copy, scene, tmp_path, capfd):
    """Just above the old 2x check pycolmap aborted (SIGABRT) in its SQLite writes: the check
    now asks for the measured peak with a margin, so the run is refused before any work."""
    size = db_copy.stat().st_size
    with db_on_small_disk(db_copy, tmp_path, leave=int(2.2 * size)) as (disk, db):
        digest = sha256(db)
        capfd.readouterr()
        code = main(["refine", "--database", str(db), "--images", str(scene.image_dir), "--workers", "1",
                     "--no-refine", "-q"])
        lines = error_lines(capfd.readouterr().err)
        assert code == 2 and len(lines) == 1 and f"not enough free space in {disk}" in lines[0], lines
        assert sha256(db) == digest and names(disk) == ["scene.db"]


def test_refine_fits_the_space_it_asks_for(db_copy, scene, tmp_path):
    """With exactly the free space the check asks for, a full run (filter, refine, write) ends."""
    from colmap_miho.adapters.working_copy import working_space

    size = db_copy.stat().st_size
    with db_on_small_disk(db_copy, tmp_path, leave=working_space(size) + 4096) as (disk, db):
        assert main(["refine", "--database", str(db), "--images", str(scene.image_dir), "--workers", "1",
                     "-q"]) == 0
        assert names(disk) == ["scene.db", "scene.miho.db"]


def test_run_checks_free_space_before_extraction(scene, tmp_path, capfd):
    with small_disk(tmp_path / "mnt", "1m") as disk:
        fill(disk, leave=64 << 10)
        capfd.readouterr()
        assert main(["run", "--images", str(scene.image_dir), "--output", str(disk / "w"), "-q"]) == 2
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and f"not enough free space in {disk / 'w'}" in lines[0], lines
        assert names(disk / "w") == []


BYPASS_SPACE_CHECK = """
import sys
import colmap_miho.adapters.safety as safety
safety.check_free_space = lambda *args, **kwargs: None  # let the disk fill during the write
from colmap_miho.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_disk_filling_during_the_write_is_one_line_not_an_abort(db_copy, scene, tmp_path):
    """The free-space check skipped (another program fills the disk meanwhile, say): SQLite's
    commit fails inside pycolmap, whose destructors would retry it and abort the process; the
    handles are kept instead and the run ends with one line, exit 1."""
    import subprocess
    import sys

    script = tmp_path / "bypass.py"
    script.write_text(BYPASS_SPACE_CHECK)
    size = db_copy.stat().st_size
    with db_on_small_disk(db_copy, tmp_path, leave=int(2.2 * size)) as (disk, db):
        digest = sha256(db)
        done = subprocess.run([sys.executable, str(script), "refine", "--database", str(db), "--images",
                               str(scene.image_dir), "--workers", "1", "--no-refine", "-q"],
                              capture_output=True, text=True, timeout=300)
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        assert done.returncode == 1, done.stderr[-2000:]
        assert len(lines) == 1 and f"disk full while writing in {disk}" in lines[0], lines
        assert sha256(db) == digest and names(disk) == [".scene.miho.db.miho-run", "scene.db"]


@pytest.mark.parametrize(("size", "inodes", "said"), [("64k", None, "MB free"), ("16m", 8, "no free inode")])
def test_a_tmpdir_where_sqlite_cannot_make_its_file_is_a_full_disk(size, inodes, said, db_copy, scene, tmp_path,
                                                                    monkeypatch, capfd):
    """A TMPDIR too small (or without a free inode) for the estimate's temporary database:
    SQLite says only "No registered database factory succeeded", COLMAP "Could not open": the
    full-disk line (the folder, what to free, the kept work and --resume), not "unexpected"."""
    out = tmp_path / "out.db"
    digest = sha256(db_copy)
    with small_disk(tmp_path / "tmp", size, inodes) as tmp:
        monkeypatch.setenv("TMPDIR", str(tmp))
        monkeypatch.setattr("tempfile.tempdir", None)  # gettempdir() reads TMPDIR again
        capfd.readouterr()
        code = main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                     "--workers", "1", "--no-refine", "--set", "match_check.mode=remove", "-q"])
        lines = error_lines(capfd.readouterr().err)
        assert code == 1 and len(lines) == 1, lines
        assert lines[0].startswith(f"ERROR: disk full in {tmp} (") and said in lines[0], lines
        assert "TMPDIR" in lines[0] and "--resume" in lines[0] and "unexpected" not in lines[0], lines
        assert list(tmp.iterdir()) == []
    assert sha256(db_copy) == digest and not out.exists()


@pytest.mark.parametrize("limit", ["half the database", "the database", "twice the database"])
def test_a_file_size_limit_is_one_message_wherever_it_is_met(limit, db_copy, scene, tmp_path):
    """``ulimit -f`` below what a run writes: met copying the database, or later by SQLite, the
    run store or a temporary database, it is one line saying so (exit 1), never "disk full" with
    gigabytes free, nor "cannot copy" with exit 2."""
    import os
    import resource
    import subprocess
    import sys

    from helpers import REPO

    size = db_copy.stat().st_size
    cap = {"half the database": size // 2, "the database": size + 4096, "twice the database": 2 * size}[limit]

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (cap, resource.RLIM_INFINITY))

    out = tmp_path / "out.db"
    path = os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])  # this checkout's package
    proc = subprocess.run([sys.executable, "-m", "colmap_miho.cli", "refine", "--database", str(db_copy),
                           "--images", str(scene.image_dir), "--output", str(out), "--workers", "1", "--no-refine",
                           "-q"], preexec_fn=limited, capture_output=True, text=True, cwd=REPO, timeout=300,
                          env={**os.environ, "PYTHONPATH": path})
    lines = error_lines(proc.stderr)
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("ERROR: file too large in "), lines
    assert f"at most {cap / 1e6:.1f} MB (ulimit -f)" in lines[0] and "disk full" not in lines[0], lines
    assert not out.exists()
