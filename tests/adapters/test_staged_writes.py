"""Every file a command writes is staged under a unique name, flushed, size-checked and renamed:
a full disk leaves no empty or short file under the target's name, and no temporary."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from disk import fill, small_disk

from colmap_miho.adapters.staged_write import private_tempdir, staged_write, write_model_atomic, write_text_atomic
from colmap_miho.cli import main
from colmap_miho.errors import RunFailed


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name != "filler")


@pytest.fixture
def model(scene, tmp_path) -> Path:
    folder = tmp_path / "model"
    folder.mkdir()
    scene.gt_reconstruction.write(str(folder))
    return folder


def test_report_ply_on_a_full_disk_is_one_line_and_leaves_nothing(model, tmp_path, capfd):
    """pycolmap's PLY writer reports no failed write: the size check against the header does."""
    with small_disk(tmp_path / "mnt", "1m") as disk:
        fill(disk)
        capfd.readouterr()
        assert main(["report", "--model", str(model), "--ply", str(disk / "points.ply"), "-q"]) == 1
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and f"disk full in {disk}" in lines[0] and "points.ply" in lines[0], lines
        assert names(disk) == []


def test_report_ply_is_whole(model, tmp_path):
    from helpers.ply import read_ply

    assert main(["report", "--model", str(model), "--ply", str(tmp_path / "p.ply"), "-q"]) == 0
    xyz, rgb = read_ply(tmp_path / "p.ply")
    assert len(xyz) == 80 and rgb is not None and names(tmp_path) == ["model", "p.ply"]


def test_report_json_on_a_full_disk_keeps_the_old_file(model, tmp_path, capfd):
    with small_disk(tmp_path / "mnt", "1m") as disk:
        old = disk / "report.json"
        old.write_text('{"old": true}')
        fill(disk)
        capfd.readouterr()
        assert main(["report", "--model", str(model), "--json", str(old), "-q"]) == 1
        lines = error_lines(capfd.readouterr().err)
        assert len(lines) == 1 and f"disk full in {disk}" in lines[0], lines
        assert json.loads(old.read_text()) == {"old": True} and names(disk) == ["report.json"]


def test_gt_model_on_a_full_disk_leaves_no_empty_file(tmp_path):
    import numpy as np

    from colmap_miho.reporting.gt_model import CameraPose, write_colmap_model

    pose = CameraPose(name="a.png", K=np.diag([500.0, 500.0, 1.0]), R=np.eye(3), t=np.zeros(3),
                      width=640, height=480)
    with small_disk(tmp_path / "mnt", "1m") as disk:
        (disk / "gt").mkdir()
        fill(disk)
        with pytest.raises(RunFailed, match="disk full in"):
            write_colmap_model({"a.png": pose}, disk / "gt")
        assert names(disk / "gt") == []


def test_model_written_whole_or_not_at_all(scene, tmp_path):
    with small_disk(tmp_path / "mnt", "1m") as disk:
        fill(disk, leave=2048)
        with pytest.raises(RunFailed, match="disk full in"):
            write_model_atomic(scene.gt_reconstruction, disk / "model")
        assert names(disk / "model") == [] and names(disk) == ["model"]
    out = write_model_atomic(scene.gt_reconstruction, tmp_path / "m")
    assert sorted(p.name for p in out.iterdir()) == ["cameras.bin", "frames.bin", "images.bin", "points3D.bin",
                                                     "rigs.bin"]


def test_json_through_a_symlink_writes_the_target_and_keeps_the_link(model, tmp_path):
    target = tmp_path / "real.json"
    target.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    assert main(["report", "--model", str(model), "--json", str(link), "-q"]) == 0
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert "reconstruction" in json.loads(target.read_text())


def test_staging_names_are_unique_and_never_a_users_file(tmp_path):
    target = tmp_path / "out.json"
    mine = [tmp_path / ".out.json.partial", tmp_path / "out.json.partial", tmp_path / ".out.json.tmp"]
    for p in mine:
        p.write_text("mine")
    with staged_write(target) as a, staged_write(tmp_path / "out.json") as b:
        assert a != b and a.parent == b.parent == tmp_path and a not in mine and b not in mine
        a.write_text("1")
        b.write_text("2")
    assert target.read_text() == "1"  # the outer one renamed last
    assert all(p.read_text() == "mine" for p in mine)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([target.name, *(p.name for p in mine)])


def test_failed_staged_write_removes_its_file(tmp_path):
    with pytest.raises(KeyError):
        with staged_write(tmp_path / "x.json") as tmp:
            tmp.write_text("half")
            raise KeyError("a writer failed")
    with pytest.raises(RunFailed, match="0 bytes written"):
        with staged_write(tmp_path / "y.json"):
            pass  # a native writer that said nothing and wrote nothing
    assert list(tmp_path.iterdir()) == []
    write_text_atomic(tmp_path / "z.json", "{}")
    assert [p.name for p in tmp_path.iterdir()] == ["z.json"]


def test_private_tempdir_is_removed_by_the_next_run_after_a_kill(tmp_path):
    """A folder left by a killed run (its lock free) is removed; a live one's is kept."""
    import subprocess
    import sys

    code = ("import os, sys; from colmap_miho.adapters.staged_write import private_tempdir\n"
            "with private_tempdir('colmap_miho_map_', sys.argv[1]) as d:\n"
            "    (d / 'database.db').write_bytes(b'x' * 1000); os._exit(9)\n")
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], check=False)
    left = list(tmp_path.glob("colmap_miho_map_*"))
    assert len(left) == 1 and (left[0] / "database.db").exists()
    user = tmp_path / "colmap_miho_map_mine"
    user.mkdir()
    with private_tempdir("colmap_miho_map_", tmp_path) as live:
        with private_tempdir("colmap_miho_map_", tmp_path) as other:
            assert live.exists() and other.exists() and not left[0].exists()
    assert [p.name for p in tmp_path.iterdir()] == ["colmap_miho_map_mine"]


def test_refine_and_map_json_through_a_symlink(db_copy, scene, tmp_path):
    for argv in (["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1",
                  "--no-refine", "--output", str(tmp_path / "out.db")],
                 ["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                  str(tmp_path / "model")]):
        target = tmp_path / f"{argv[0]}-real.json"
        target.write_text("{}")
        link = tmp_path / f"{argv[0]}.json"
        link.symlink_to(target)
        assert main([*argv, "--json", str(link), "-q"]) == 0
        assert link.is_symlink() and os.readlink(link) == str(target)
        assert json.loads(target.read_text()) != {}


def test_a_new_file_never_replaces_one_that_appeared_meanwhile(tmp_path):
    """import's last step: a database another run published first is kept, this one refused."""
    from colmap_miho.adapters.working_copy import publish_new_file
    from colmap_miho.errors import UserError

    theirs = tmp_path / "new.db"
    ours = tmp_path / "ours.tmp"
    ours.write_bytes(b"ours")
    publish_new_file(ours, theirs)
    assert theirs.read_bytes() == b"ours" and not ours.exists()
    again = tmp_path / "again.tmp"
    again.write_bytes(b"second")
    with pytest.raises(UserError, match="created by another program during the run"):
        publish_new_file(again, theirs)
    assert theirs.read_bytes() == b"ours"


_STRESS = """
import os, sys
from colmap_miho.adapters.staged_write import private_tempdir
failures = 0
for i in range(int(sys.argv[2])):
    try:
        with private_tempdir("colmap_miho_map_", sys.argv[1]) as d:
            (d / "database.db").write_bytes(b"x" * 100)
            os.sched_yield()
            if (d / "database.db").read_bytes() != b"x" * 100:
                failures += 1
    except OSError as exc:
        failures += 1
        print(type(exc).__name__, exc, file=sys.stderr)
print(failures)
"""


def test_private_tempdir_runs_at_once_never_remove_each_others_folder(tmp_path):
    """Four runs making and sweeping private folders in one parent, 300 times each: a sweep
    must never take a live run's folder (its lock file existed, unlocked, for a moment)."""
    import subprocess
    import sys

    procs = [subprocess.Popen([sys.executable, "-c", _STRESS, str(tmp_path), "300"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(4)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [int(out.split()[-1]) for out, _ in outs] == [0, 0, 0, 0], [err[-500:] for _, err in outs]
    assert list(tmp_path.iterdir()) == []


def test_private_tempdir_killed_before_its_lock_is_removed_later(tmp_path, monkeypatch):
    """A run killed between making its folder and locking it leaves the folder with only its
    pending lock file: removed once older than PENDING_TEMPDIR_S; an empty one (a run that has
    not made its lock yet) or one with other files is never taken."""
    from colmap_miho.adapters import staged_write as sw

    killed = tmp_path / "colmap_miho_map_killed"
    killed.mkdir()
    (killed / f"{sw._PENDING_LOCK}abc").touch()
    empty = tmp_path / "colmap_miho_map_empty"
    empty.mkdir()
    user = tmp_path / "colmap_miho_map_user"
    user.mkdir()
    (user / f"{sw._PENDING_LOCK}abc").touch()
    (user / "notes.txt").touch()
    with private_tempdir("colmap_miho_map_", tmp_path):
        pass
    assert killed.exists()  # young: its run may be about to lock it
    monkeypatch.setattr(sw, "PENDING_TEMPDIR_S", -1.0)
    with private_tempdir("colmap_miho_map_", tmp_path):
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colmap_miho_map_empty", "colmap_miho_map_user"]
