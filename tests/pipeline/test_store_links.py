"""The run store is never reached through a symbolic link, and never deletes what it did not
create: a link in place of its folder or of one of its files is refused with one line naming
it (the link's target is left as it was), and clearing or removing the store takes only the
store's own files."""

from __future__ import annotations

import os

import numpy as np
import pytest

from colmap_miho.errors import UserError
from colmap_miho.pipeline.store import RunStore, store_folder

FINGERPRINT = {"database": "abc", "seed": 0}
PLAN = {"budget": 1}


def _victim(tmp_path):
    """A folder of someone else's files (and a subfolder), to be left as it is."""
    victim = tmp_path / "victim"
    (victim / "sub").mkdir(parents=True)
    (victim / "data.txt").write_text("keep me")
    (victim / "sub" / "more.txt").write_text("keep me too")
    (victim / "manifest.json").write_text("{}")
    return victim


def _contents(folder):
    return sorted((str(p.relative_to(folder)), p.read_text() if p.is_file() else None) for p in folder.rglob("*"))


def _stored(folder, values=(1.0,)):
    store = RunStore.open(folder, FINGERPRINT)
    store.refine_groups(PLAN)
    for index, value in enumerate(values):
        store.save_group(index, {1: (np.array([0, 1]), np.full((2, 2), float(value)))}, {"moved": 2})
    store.close()


@pytest.mark.parametrize("resume", [False, True])
def test_a_linked_store_folder_is_refused(resume, tmp_path):
    victim = _victim(tmp_path)
    before = _contents(victim)
    folder = store_folder(tmp_path / "out" / "o.db")
    folder.parent.mkdir()
    folder.symlink_to(victim, target_is_directory=True)
    with pytest.raises(UserError, match=rf"run folder {folder} is a symbolic link .*remove the link"):
        RunStore.open(folder, FINGERPRINT, resume=resume)
    with pytest.raises(UserError, match="symbolic link"):
        RunStore.open(folder, FINGERPRINT, restart=True)
    assert _contents(victim) == before and folder.is_symlink()


def test_a_dangling_link_in_place_of_the_store_folder_is_refused(tmp_path):
    folder = tmp_path / ".o.db.miho-run"
    folder.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(UserError, match="is a symbolic link"):
        RunStore.open(folder, FINGERPRINT)
    assert not (tmp_path / "elsewhere").exists()


@pytest.mark.parametrize("name", ["lock", "manifest.json", "group-000000.npz", "group-000007.npz",
                                  "stage-match_check.npz", "filter-000000.npz", ".group-000001.npz.k2j3_x.tmp"])
@pytest.mark.parametrize("restart", [False, True])
def test_a_link_in_place_of_a_store_file_is_refused(name, restart, tmp_path):
    folder = tmp_path / "store"
    _stored(folder)
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    (folder / name).unlink(missing_ok=True)
    (folder / name).symlink_to(target)
    with pytest.raises(UserError, match=rf"{name} is a symbolic link.*remove it"):
        RunStore.open(folder, FINGERPRINT, resume=not restart, restart=restart)
    assert target.read_text() == "keep me" and (folder / name).is_symlink()


def test_a_folder_in_place_of_a_store_file_is_refused(tmp_path):
    folder = tmp_path / "store"
    _stored(folder)
    (folder / "group-000003.npz").mkdir()
    (folder / "group-000003.npz" / "x").write_text("keep me")
    with pytest.raises(UserError, match=r"group-000003.npz is not a regular file"):
        RunStore.open(folder, FINGERPRINT, restart=True)
    assert (folder / "group-000003.npz" / "x").read_text() == "keep me"


def test_restart_and_remove_take_only_the_stores_own_files(tmp_path):
    folder = tmp_path / "store"
    _stored(folder, [1.0, 2.0])
    (folder / "notes.txt").write_text("someone's")
    (folder / "sub").mkdir()
    (folder / "sub" / "x").write_text("someone's")
    (folder / ".group-000000.npz.abc123.tmp").write_bytes(b"half a file")  # a write cut short: ours
    store = RunStore.open(folder, FINGERPRINT, restart=True)
    assert sorted(p.name for p in folder.iterdir()) == ["lock", "manifest.json", "notes.txt", "sub"]
    store.remove()
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt", "sub"]
    assert (folder / "sub" / "x").read_text() == "someone's"


def test_remove_deletes_the_whole_store_when_it_holds_only_its_own_files(tmp_path):
    folder = tmp_path / "store"
    _stored(folder, [1.0])
    store = RunStore.open(folder, FINGERPRINT, resume=True)
    store.remove()
    assert not os.path.lexists(folder)


def test_refine_with_a_linked_store_folder_stops_with_one_line(tmp_path, capsys):
    """``refine --output out/o.db`` with ``out/.o.db.miho-run`` a link: exit 2, one line, and the
    link's folder as it was (an earlier version emptied it)."""
    from colmap_miho.cli import main
    from miho_bench.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(tmp_path / "scene", num_images=3, num_points=40, seed=5)
    victim = _victim(tmp_path)
    before = _contents(victim)
    out = tmp_path / "out" / "o.db"
    out.parent.mkdir()
    store_folder(out).symlink_to(victim, target_is_directory=True)
    args = ["refine", "--database", str(scene.database), "--images", str(scene.image_dir), "--output", str(out),
            "--workers", "1", "--device", "cpu", "-q"]
    for extra in ([], ["--resume"], ["--restart"]):
        capsys.readouterr()
        assert main(args + extra) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and str(store_folder(out)) in lines[0] and "symbolic link" in lines[0], lines
        assert _contents(victim) == before and not out.exists()
        assert sorted(p.name for p in out.parent.iterdir()) == [store_folder(out).name]  # no working copy left


def test_a_file_in_place_of_the_store_folder_is_named(tmp_path):
    """A file where the run folder belongs (it said only "File exists")."""
    folder = store_folder(tmp_path / "o.db")
    folder.write_text("mine")
    with pytest.raises(UserError, match=rf"{folder} is a file, not the run folder.*remove it or choose another"):
        RunStore.open(folder, FINGERPRINT)
    assert folder.read_text() == "mine"
