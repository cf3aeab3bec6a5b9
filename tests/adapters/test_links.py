"""No file or folder that colmap-miho makes, clears or removes is reached through a symbolic
link: a link in its place is refused with one line (exit 2) naming it, or passed over for a
free name, and the link's target is never written, emptied or deleted. (The run store has its
own tests: ``tests/pipeline/test_store_links.py``.)"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from colmap_miho.adapters import safety, staged_write
from colmap_miho.adapters.paths import comparison_paths
from colmap_miho.adapters.safety import backup_path, copy_file
from colmap_miho.adapters.working_copy import WorkingCopy
from colmap_miho.errors import UserError

STAMP = "20260101-120000"


def _victim(tmp_path):
    """Someone else's folder, with the names a job writes."""
    victim = tmp_path / "victim"
    victim.mkdir()
    for name in ("database.db", "refine.json", "compare.md", "report.json", "cameras.bin"):
        (victim / name).write_text(f"someone's {name}")
    return victim


def _last(name: str) -> str:
    """The file name of a relative path."""
    return name.rsplit("/", 1)[-1]


def _contents(folder):
    return sorted((p.name, p.read_text()) for p in folder.iterdir())


# -- the folders and files `compare` and `run` make in their --output --------------------------
@pytest.mark.parametrize("compare, linked", [
    *((True, name) for name in ("refined", "baseline", "plots", "refined/model", "baseline/model", "baseline/runs")),
    (False, "refined"), (False, "refined/model"),  # run makes no baseline or plots
])
def test_a_link_in_place_of_a_job_folder_is_refused(compare, linked, tmp_path):
    victim, images, out = _victim(tmp_path), tmp_path / "images", tmp_path / "out"
    images.mkdir()
    before = _contents(victim)
    (out / linked).parent.mkdir(parents=True, exist_ok=True)
    (out / linked).symlink_to(victim, target_is_directory=True)
    with pytest.raises(UserError, match=rf"--output \({linked}.*\) .* is a symbolic link \(to {victim}\).*remove the "
                                        "link or choose another --output"):
        comparison_paths(out, images=images, database=tmp_path / "in.db" if compare else None, compare=compare,
                         repeats=2)
    assert _contents(victim) == before


@pytest.mark.parametrize("name", ["refined/refine.json", "refined/database.db", "compare.md", "report.json"])
def test_a_link_in_place_of_a_job_file_is_refused(name, tmp_path):
    compare = name != "report.json"
    victim, images, out = _victim(tmp_path), tmp_path / "images", tmp_path / "out"
    images.mkdir()
    (out / name).parent.mkdir(parents=True, exist_ok=True)
    (out / name).symlink_to(victim / _last(name))
    with pytest.raises(UserError, match=rf"{out / name} is a symbolic link"):
        comparison_paths(out, images=images, database=tmp_path / "in.db" if compare else None, compare=compare)
    assert (victim / _last(name)).read_text() == f"someone's {_last(name)}"


def test_run_reuses_a_linked_database_it_reads(tmp_path):
    """``run``'s ``OUTPUT/database.db``, when it exists, is an input (reused): a link there is the
    user's way to give it."""
    victim, images, out = _victim(tmp_path), tmp_path / "images", tmp_path / "out"
    images.mkdir()
    out.mkdir()
    (out / "database.db").symlink_to(victim / "database.db")
    inputs, _ = comparison_paths(out, images=images, compare=False)
    assert "--output (database.db, reused)" in inputs


# -- in-place backups and kept results --------------------------------------------------------
def test_a_backup_name_held_by_a_dangling_link_is_passed_over(tmp_path, monkeypatch):
    db = tmp_path / "scene.db"
    db.write_bytes(b"x")
    monkeypatch.setattr(safety.time, "strftime", lambda *args: STAMP)
    link = tmp_path / f"scene.db.{STAMP}.bak"
    link.symlink_to(tmp_path / "elsewhere" / "stolen.db")
    assert backup_path(db) == tmp_path / f"scene.db.{STAMP}-1.bak"


def test_copy_file_never_writes_through_a_link(tmp_path):
    src, target = tmp_path / "a.db", tmp_path / "target.db"
    src.write_bytes(b"new bytes")
    target.write_bytes(b"someone's")
    (tmp_path / "link.db").symlink_to(target)
    (tmp_path / "dangling.db").symlink_to(tmp_path / "made-elsewhere.db")
    for name in ("link.db", "dangling.db"):
        with pytest.raises(UserError, match=rf"{tmp_path / name} is a symbolic link"):
            copy_file(src, tmp_path / name)
        assert (tmp_path / name).is_symlink()
    assert target.read_bytes() == b"someone's" and not (tmp_path / "made-elsewhere.db").exists()


def test_an_in_place_run_never_backs_up_through_a_link(db_copy, monkeypatch):
    monkeypatch.setattr(safety.time, "strftime", lambda *args: STAMP)
    link = db_copy.with_name(f"{db_copy.name}.{STAMP}.bak")
    elsewhere = db_copy.parent.parent / "elsewhere.db"
    link.symlink_to(elsewhere)
    with WorkingCopy(db_copy, in_place=True) as wc:
        assert wc.backup is not None and wc.backup != link and not wc.backup.is_symlink()
    assert link.is_symlink() and not elsewhere.exists()


# -- private temporary folders ------------------------------------------------------------------
def test_the_sweep_never_takes_a_link_to_a_folder(tmp_path):
    """A link named like a stale temporary folder, to a folder with a free lock file: left alone."""
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / ".colmap-miho.lock").write_text("")
    (victim / "data.txt").write_text("keep me")
    (tmp_path / "miho-global-abc").symlink_to(victim, target_is_directory=True)
    staged_write.sweep_stale_tempdirs(tmp_path)
    assert (victim / "data.txt").read_text() == "keep me" and (tmp_path / "miho-global-abc").is_symlink()


def test_a_private_tempdir_replaced_by_a_link_is_not_emptied(tmp_path):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "data.txt").write_text("keep me")
    with staged_write.private_tempdir("miho-global-", tmp_path) as path:
        moved = tmp_path / "moved"
        os.rename(path, moved)
        path.symlink_to(victim, target_is_directory=True)
    assert (victim / "data.txt").read_text() == "keep me"


@pytest.mark.parametrize("linked", ["scene", "scene/images", "scene/gt_model"])
def test_demo_never_writes_its_scene_through_a_link(linked, tmp_path, capsys):
    pytest.importorskip("skimage")
    pytest.importorskip("matplotlib")
    from colmap_miho.cli import main

    victim, out = _victim(tmp_path), tmp_path / "demo"
    before = _contents(victim)
    (out / linked).parent.mkdir(parents=True, exist_ok=True)
    (out / linked).symlink_to(victim, target_is_directory=True)
    assert main(["demo", "--output", str(out), "--quick", "-q"]) == 2
    err = capsys.readouterr().err
    assert f"{out / linked} is a symbolic link" in err and "remove the link" in err, err
    assert _contents(victim) == before


# -- working copies, staged writes, staged models: our own new names, removed by unlink ---------
def test_a_working_copy_replaced_by_a_link_leaves_the_target(db_copy, tmp_path):
    target = tmp_path / "precious.db"
    target.write_text("keep me")
    with WorkingCopy(db_copy, tmp_path / "out.db") as wc:
        assert wc.path is not None
        wc.path.unlink()
        wc.path.symlink_to(target)
        Path(str(wc.path) + "-wal").symlink_to(target)
        links = [wc.path, Path(str(wc.path) + "-wal")]
    assert target.read_text() == "keep me"
    assert all(link.is_symlink() for link in links)  # not ours: left as they are


def test_a_staged_file_replaced_by_a_link_leaves_the_target(tmp_path):
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    with pytest.raises(RuntimeError, match="stop"):
        with staged_write.staged_write(tmp_path / "out.txt") as tmp:
            tmp.unlink()
            tmp.symlink_to(target)
            raise RuntimeError("stop")
    assert target.read_text() == "keep me" and not (tmp_path / "out.txt").exists() and tmp.is_symlink()


def test_a_model_stage_replaced_by_a_link_is_not_emptied(tmp_path, monkeypatch):
    import tempfile

    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "data.txt").write_text("keep me")
    real = tempfile.mkdtemp

    def mkdtemp(*args, **kwargs):
        made = Path(real(*args, **kwargs))
        made.rmdir()
        made.symlink_to(victim, target_is_directory=True)
        return str(made)

    class Model:
        def write(self, folder):
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(tempfile, "mkdtemp", mkdtemp)
    with pytest.raises(Exception, match="disk full"):
        staged_write.write_model_atomic(Model(), tmp_path / "model")
    assert (victim / "data.txt").read_text() == "keep me"


@pytest.mark.parametrize("suffix", ["-wal", "-journal"])
def test_a_link_beside_a_new_working_copy_is_refused_before_sqlite_opens_it(suffix, db_copy, tmp_path, monkeypatch):
    """A link made at the working copy's -wal while the database is copied: SQLite would write
    its journal into the link's target."""
    from colmap_miho.adapters import working_copy

    target = tmp_path / "precious.db"
    target.write_text("keep me")
    real = working_copy.copy_file

    def copy_and_plant(src, dst):
        real(src, dst)
        if str(dst).endswith(".tmp"):
            Path(str(dst) + suffix).symlink_to(target)

    monkeypatch.setattr(working_copy, "copy_file", copy_and_plant)
    out = tmp_path / "out.db"
    with pytest.raises(UserError, match=rf"{suffix} appeared beside the working copy .* symbolic link .*remove it"):
        with WorkingCopy(db_copy, out):
            pass
    assert target.read_text() == "keep me"
    left = [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.db.")]
    assert len(left) == 1 and left[0].endswith(suffix)  # only the link, left as it is


@pytest.mark.parametrize("name", ["cameras.bin", "cameras.txt"])
def test_a_model_written_over_a_link_leaves_its_target(name, scene, tmp_path):
    """A model file of either format that is a link: the new model's file replaces the link
    (.bin) or the link is left (.txt, the other format, which a write removes when it is a file);
    the link's target is never written or removed."""
    victim = tmp_path / "victim.bin"
    victim.write_text("keep me")
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / name).symlink_to(victim)
    staged_write.write_model_atomic(scene.gt_reconstruction, folder)
    assert victim.read_text() == "keep me" and (folder / "cameras.bin").is_file()
    assert (folder / name).is_symlink() == (name == "cameras.txt")
