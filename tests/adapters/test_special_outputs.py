"""Outputs never replace a special file: only a regular file (or nothing) is replaced.

A character device (``/dev/null``, a terminal) is written through; a FIFO, a socket, a block
device or a folder is refused with one line naming the option, before any work.
"""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest

from colmap_miho.adapters.staged_write import check_output_path, write_text_atomic
from colmap_miho.cli import main
from colmap_miho.errors import UserError

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="creating a device node (mknod) needs root")


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def _null_device(path: Path) -> Path:
    """A character device node like /dev/null (major 1, minor 3) at ``path``."""
    os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    return path


def _special(kind: str, path: Path) -> Path:
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "socket":
        sock = socket.socket(socket.AF_UNIX)
        sock.bind(str(path))
        sock.close()
    elif kind == "folder":
        path.mkdir()
    return path


@pytest.mark.parametrize("kind", ["fifo", "socket", "folder"])
def test_staged_write_refuses_what_is_not_a_regular_file(kind, tmp_path):
    target = _special(kind, tmp_path / "out.json")
    mode = os.lstat(target).st_mode
    with pytest.raises(UserError, match="not a regular file|is a folder"):
        write_text_atomic(target, "{}")
    assert os.lstat(target).st_mode == mode


def test_staged_write_refuses_a_fifo_behind_a_symlink(tmp_path):
    fifo = _special("fifo", tmp_path / "pipe")
    link = tmp_path / "out.json"
    link.symlink_to(fifo)
    with pytest.raises(UserError, match="FIFO"):
        write_text_atomic(link, "{}")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and link.is_symlink()


@needs_root
def test_staged_write_writes_through_a_character_device(tmp_path):
    dev = _null_device(tmp_path / "mynull")
    write_text_atomic(dev, '{"a": 1}')
    assert stat.S_ISCHR(os.lstat(dev).st_mode)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_dev_null_is_written_through_not_replaced():
    before = os.stat("/dev/null")
    write_text_atomic("/dev/null", "nothing")
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and (before.st_ino, before.st_rdev) == (after.st_ino, after.st_rdev)


def test_check_output_path_names_the_option(tmp_path):
    fifo = _special("fifo", tmp_path / "p")
    with pytest.raises(UserError, match=r"^--json .*/p is a FIFO \(named pipe\), not a regular file"):
        check_output_path(fifo, "--json")
    assert check_output_path(tmp_path / "new.json", "--json") is None
    assert check_output_path("/dev/null", "--output", device=True) == "character device"
    with pytest.raises(UserError, match="--output /dev/null is a character device"):
        check_output_path("/dev/null", "--output", device=False)


@pytest.mark.parametrize("option", ["--json", "--ply", "--html"])
@pytest.mark.parametrize("kind", ["fifo", "socket"])
def test_report_outputs_refuse_special_files(option, kind, model, tmp_path, capfd):
    target = _special(kind, tmp_path / f"out{option[2:]}")
    capfd.readouterr()
    assert main(["report", "--model", str(model), option, str(target), "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and option in lines[0] and str(target) in lines[0], lines
    assert not stat.S_ISREG(os.lstat(target).st_mode)


@needs_root
@pytest.mark.parametrize("option", ["--json", "--ply"])
def test_report_writes_through_a_character_device(option, model, tmp_path, capfd):
    dev = _null_device(tmp_path / "mynull")
    assert main(["report", "--model", str(model), option, str(dev), "-q"]) == 0
    assert stat.S_ISCHR(os.lstat(dev).st_mode)


def test_refine_output_fifo_is_refused_even_with_overwrite(db_copy, scene, tmp_path, capfd):
    fifo = _special("fifo", tmp_path / "out.db")
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(fifo),
                 "--overwrite", "--no-refine", "--workers", "1", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--output" in lines[0] and "FIFO" in lines[0], lines
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


@needs_root
def test_refine_output_character_device_is_refused(db_copy, scene, tmp_path, capfd):
    dev = _null_device(tmp_path / "mynull")
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(dev),
                 "--overwrite", "--no-refine", "--workers", "1", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--output" in lines[0] and "character device" in lines[0], lines
    assert stat.S_ISCHR(os.lstat(dev).st_mode)


@needs_root
def test_refine_json_writes_through_a_character_device(db_copy, scene, tmp_path):
    dev = _null_device(tmp_path / "mynull")
    out = tmp_path / "out.db"
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--json", str(dev), "--no-refine", "--workers", "1", "-q"]) == 0
    assert stat.S_ISCHR(os.lstat(dev).st_mode) and out.is_file()


@pytest.mark.parametrize("option", ["--features", "--matches"])
def test_export_refuses_a_fifo_even_with_overwrite(option, db_copy, tmp_path, capfd):
    fifo = _special("fifo", tmp_path / "x.h5")
    other = "--matches" if option == "--features" else "--features"
    capfd.readouterr()
    assert main(["export", "--database", str(db_copy), option, str(fifo), other, str(tmp_path / "o.h5"),
                 "--overwrite", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and option in lines[0] and "FIFO" in lines[0], lines
    assert not (tmp_path / "o.h5").exists()


@needs_root
def test_export_writes_through_a_character_device(db_copy, tmp_path):
    dev = _null_device(tmp_path / "mynull")
    assert main(["export", "--database", str(db_copy), "--features", str(dev), "--matches",
                 str(tmp_path / "m.h5"), "--overwrite", "-q"]) == 0
    assert stat.S_ISCHR(os.lstat(dev).st_mode)


def test_map_json_fifo_is_refused_before_mapping(db_copy, scene, tmp_path, capfd):
    fifo = _special("fifo", tmp_path / "map.json")
    capfd.readouterr()
    assert main(["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                 str(tmp_path / "model"), "--json", str(fifo), "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--json" in lines[0] and "FIFO" in lines[0], lines
    assert not (tmp_path / "model").exists()


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full here")
def test_refine_json_to_a_full_device_commits_nothing_and_its_advice_works(db_copy, scene, tmp_path, capfd):
    """``--json /dev/full``: the summary cannot be written, so nothing is committed (a result
    without its summary, with advice to --resume that then fails on the existing output, lost
    the summary); the line says so and where, and its advice (--resume) finishes the run."""
    out = tmp_path / "out.db"
    args = ["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
            "--no-refine", "--workers", "1", "-q"]
    capfd.readouterr()
    assert main([*args, "--json", "/dev/full"]) == 1
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "/dev/full" in lines[0] and "--resume" in lines[0], lines
    assert not out.exists()
    assert main([*args, "--json", str(tmp_path / "s.json"), "--resume"]) == 0
    assert out.is_file() and (tmp_path / "s.json").is_file()


def test_refine_json_that_fails_after_the_commit_says_the_output_was_written(db_copy, scene, tmp_path, capfd,
                                                                             monkeypatch):
    """The one step after the commit, renaming ``--json`` onto its name, failing: the line says
    the output was written (no --resume, which would fail on it) and the run store goes."""
    from colmap_miho.adapters import working_copy
    from colmap_miho.pipeline.store import store_folder

    real = os.replace

    def replace(src, dst, *args, **kwargs):
        if str(dst).endswith("s.json"):
            raise IsADirectoryError(21, "Is a directory")
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(working_copy.os, "replace", replace)
    out, summary = tmp_path / "out.db", tmp_path / "s.json"
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--json", str(summary), "--no-refine", "--workers", "1", "-q"]) == 1
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"{out} was written" in lines[0] and str(summary) in lines[0], lines
    assert "--resume" not in lines[0] and "--overwrite" in lines[0]
    assert out.is_file() and not summary.exists() and not os.path.lexists(store_folder(out))


def test_refine_json_to_a_device_in_a_folder_this_user_cannot_write(db_copy, scene, tmp_path, monkeypatch):
    """A user who is not root cannot write in ``/dev``: ``--json /dev/stdout`` (written through,
    never replaced) was refused as a read-only folder."""
    real = os.access

    def access(path, mode, *args, **kwargs):  # as for a user who is not root
        return False if Path(path) == Path("/dev") and mode & os.W_OK else real(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", access)
    out = tmp_path / "out.db"
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--json", "/dev/null", "--no-refine", "--workers", "1", "-q"]) == 0
    assert out.is_file()


def test_refine_json_to_a_device_stages_no_file_in_tmpdir(db_copy, scene, tmp_path, monkeypatch):
    """The summary for a device waits in memory until the commit: a file staged in ``$TMPDIR``
    outlived a ``kill -9`` there, and no later run removed it."""
    import tempfile

    from colmap_miho.adapters.working_copy import WorkingCopy

    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmpdir))
    seen: list[list[str]] = []
    commit = WorkingCopy.commit

    def looking(self):
        seen.append(sorted(os.listdir(tmpdir)))  # what a kill -9 now would leave
        return commit(self)

    monkeypatch.setattr(WorkingCopy, "commit", looking)
    out = tmp_path / "out.db"
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--json", "/dev/null", "--no-refine", "--workers", "1", "-q"]) == 0
    assert seen == [[]] and out.is_file() and not os.listdir(tmpdir)


def test_refine_json_link_into_a_missing_folder_is_refused_before_any_work(db_copy, scene, tmp_path, capfd):
    """A ``--json`` symbolic link whose target's folder is missing: refused at the start, naming
    the link (the whole run was done first, then failed on it)."""
    from colmap_miho.pipeline.store import store_folder

    link = tmp_path / "s.json"
    link.symlink_to(tmp_path / "nowhere" / "s.json")
    out = tmp_path / "out.db"
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--json", str(link), "--no-refine", "--workers", "1", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--json" in lines[0] and "nowhere" in lines[0] and str(link) in lines[0], lines
    assert not out.exists() and not os.path.lexists(store_folder(out))


def test_a_file_for_a_device_is_staged_where_the_next_run_sweeps(model, tmp_path, monkeypatch):
    """``report --json /dev/null`` (``map``, ``export`` alike) stages the file in ``$TMPDIR``: in
    a locked folder of ours, which the next command removes should a ``kill -9`` leave it (a bare
    ``.null.*.tmp`` there stayed for ever)."""
    import tempfile

    from colmap_miho.adapters import staged_write

    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmpdir))
    seen: list[list[str]] = []
    write_through = staged_write.write_through

    def looking(tmp, device):
        seen.append(sorted(os.listdir(tmpdir)))  # what a kill -9 now would leave
        return write_through(tmp, device)

    monkeypatch.setattr(staged_write, "write_through", looking)
    assert main(["report", "--model", str(model), "--json", "/dev/null", "-q"]) == 0
    assert seen and seen[0] and all(n.startswith(staged_write.TMPDIR_PREFIXES) for n in seen[0]), seen
    assert not os.listdir(tmpdir)


@pytest.mark.parametrize("name", ["manifest.json", "notes.json"])
def test_refine_json_inside_the_run_folder_is_refused(name, db_copy, scene, tmp_path, capfd):
    """The run folder is removed after the commit: ``--json`` there as ``manifest.json`` went
    with it, exit 0 all the same."""
    from colmap_miho.pipeline.store import store_folder

    out = tmp_path / "out.db"
    folder = store_folder(out)
    folder.mkdir()
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--json", str(folder / name), "--no-refine", "--workers", "1", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "--json" in lines[0] and "inside the run folder" in lines[0], lines
    assert not out.exists() and sorted(os.listdir(folder)) == []


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full here")
def test_report_json_to_a_full_device_names_the_device(model, capfd):
    """(the line named the staging folder in $TMPDIR, with its free space, as the full disk)"""
    capfd.readouterr()
    assert main(["report", "--model", str(model), "--json", "/dev/full", "-q"]) == 1
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("ERROR: disk full while writing /dev/full"), lines
    assert "colmap_miho_device_" not in lines[0] and "MB free" not in lines[0], lines
