"""Inputs are bounded before they are read: h5 shapes and dtypes against the memory budget,
finite values, repeated match rows, lying blob sizes in a database."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import h5py
import numpy as np
import pytest

from colmap_miho.cli import main


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


@pytest.fixture
def exported(scene, tmp_path) -> tuple[Path, Path]:
    feats, matches = tmp_path / "features.h5", tmp_path / "matches.h5"
    assert main(["export", "--database", str(scene.database), "--features", str(feats), "--matches",
                 str(matches), "--layout", "dim", "-q"]) == 0
    return feats, matches


def _import(scene, feats: Path, matches: Path, db: Path) -> list[str]:
    return ["import", "--features", str(feats), "--matches", str(matches), "--images", str(scene.image_dir),
            "--database", str(db), "--no-verify", "-q"]


def _replace_keypoints(feats: Path, **dataset) -> str:
    with h5py.File(feats, "r+") as fh:
        name = next(iter(fh))
        while "keypoints" not in fh[name]:
            name = f"{name}/{next(iter(fh[name]))}"
        del fh[name]["keypoints"]
        fh[name].create_dataset("keypoints", **dataset)
    return name


@pytest.mark.parametrize("case, message", [
    ("huge", r"keypoints of image .* \(400000000 rows\) would take \d+ MiB in memory, more than the budget"),
    ("bool", "keypoints of image .* have dtype bool, expected real numbers"),
    ("complex", "keypoints of image .* have dtype complex64, expected real numbers"),
    ("nan", "keypoints of image .* contain NaN or inf"),
])
def test_h5_keypoints_are_checked_before_reading(case, message, scene, exported, tmp_path, capfd):
    """A 4e8 x 2 gzip dataset of zeros (a file of kilobytes) is refused from its shape alone."""
    import re

    feats, matches = exported
    dataset = {
        "huge": {"shape": (400_000_000, 2), "dtype": "f4", "compression": "gzip", "chunks": (1 << 16, 2)},
        "bool": {"data": np.ones((80, 2), bool)},
        "complex": {"data": np.ones((80, 2), np.complex64)},
        "nan": {"data": np.full((80, 2), np.nan, np.float32)},
    }[case]
    _replace_keypoints(feats, **dataset)
    assert feats.stat().st_size < 10**6
    capfd.readouterr()
    assert main(_import(scene, feats, matches, tmp_path / "new.db")) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and re.search(message, lines[0]) and str(feats) in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["features.h5", "matches.h5"]


def test_h5_matches_larger_than_the_pair_allows_are_refused(scene, exported, tmp_path, capfd):
    feats, matches = exported
    with h5py.File(matches, "r+") as mh:
        name0 = next(iter(mh))
        name1 = next(iter(mh[name0]))
        del mh[name0][name1]
        mh[name0].create_dataset(name1, shape=(10**9, 2), dtype="i4", compression="gzip", chunks=(1 << 16, 2))
    capfd.readouterr()
    assert main(_import(scene, feats, matches, tmp_path / "new.db")) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "1000000000 matches, more than the" in lines[0], lines


def test_repeated_match_rows_are_dropped_with_a_warning(scene, exported, tmp_path, capfd):
    feats, matches = exported
    with h5py.File(matches, "r+") as mh:
        name0 = next(iter(mh))
        name1 = next(iter(mh[name0]))
        m = mh[name0][name1][()]
        del mh[name0][name1]
        mh[name0].create_dataset(name1, data=np.concatenate([m, m[:5]]))
    capfd.readouterr()
    assert main(_import(scene, feats, matches, tmp_path / "new.db")[:-1]) == 0
    err = capfd.readouterr().err
    assert "5 repeated match rows dropped" in err and name0 in err, err
    con = sqlite3.connect(tmp_path / "new.db")
    rows = sorted(r[0] for r in con.execute("SELECT rows FROM matches"))
    con.close()
    assert len(m) in rows and len(m) + 5 not in rows
