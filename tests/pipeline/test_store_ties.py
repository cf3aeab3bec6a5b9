"""The run store's files belong to the run that wrote them: a valid ``.npz`` copied in from
another run's store, or renamed within one, is refused on ``--resume`` (it would be trusted as
finished work of this run and written into the output)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from colmap_miho.pipeline.store import RunStore, StoreDamaged

FINGERPRINT = {"database": "abc", "seed": 0}
PLAN = {"budget": 1}


def _store_with_groups(folder, values) -> None:
    store = RunStore.open(folder, FINGERPRINT)
    store.refine_groups(PLAN)  # records the plan the groups belong to
    for index, value in enumerate(values):
        store.save_group(index, {1: (np.array([0, 1]), np.full((2, 2), float(value)))}, {"moved": 2})
    store.save_stage("match_check", {"pairs": np.zeros((0, 2), np.int64)}, {"used": False})
    store.close()


def test_an_untouched_store_resumes(tmp_path):
    _store_with_groups(tmp_path / "a", [1.0, 2.0])
    store = RunStore.open(tmp_path / "a", FINGERPRINT, resume=True)
    groups = store.refine_groups(PLAN)
    assert [float(groups[i][0][1][1][0, 0]) for i in (0, 1)] == [1.0, 2.0]
    assert store.load_stage("match_check")[1] == {"used": False}
    store.close()


@pytest.mark.parametrize("name", ["group-000000.npz", "stage-match_check.npz"])
def test_a_file_of_another_run_is_not_trusted(name, tmp_path):
    _store_with_groups(tmp_path / "a", [1.0])
    _store_with_groups(tmp_path / "b", [9.0])  # the same inputs: a valid file, another run's
    shutil.copyfile(tmp_path / "b" / name, tmp_path / "a" / name)
    store = RunStore.open(tmp_path / "a", FINGERPRINT, resume=True)
    with pytest.raises(StoreDamaged, match=rf"{name} is damaged \(it was written by another run.*--restart"):
        store.refine_groups(PLAN) if name.startswith("group") else store.load_stage("match_check")
    store.close()


def test_a_renamed_file_is_not_trusted(tmp_path):
    _store_with_groups(tmp_path / "a", [1.0, 2.0])
    folder = tmp_path / "a"
    (folder / "group-000000.npz").rename(folder / "x.npz")
    (folder / "group-000001.npz").rename(folder / "group-000000.npz")
    (folder / "x.npz").rename(folder / "group-000001.npz")
    store = RunStore.open(folder, FINGERPRINT, resume=True)
    with pytest.raises(StoreDamaged, match=r"it was written as group-000001.npz, not under this name"):
        store.refine_groups(PLAN)
    store.close()
