"""Bad input a careless user gives: one line naming the option or file, exit 2."""

from __future__ import annotations

import os

import pytest

from colmap_miho.cli import main
from colmap_miho.errors import InvalidInput
from colmap_miho.recipe import load_recipe


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


# ------------------------------------------------------------------ recipes
def test_a_recipe_with_a_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "windows.toml"
    path.write_bytes(b"\xef\xbb\xbf[filter]\nt_l = 12\n")
    assert load_recipe(str(path)).filter.t_l == 12


@pytest.mark.parametrize(("kind", "said"), [("fifo", "FIFO"), ("folder", "folder"), ("device", "character device")])
def test_a_recipe_path_that_is_not_a_file_says_what_it_is(kind, said, tmp_path):
    path = tmp_path / "r.toml"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    else:
        path = "/dev/zero"
    with pytest.raises(InvalidInput, match=f"recipe {path} is a {said}"):
        load_recipe(str(path))


@pytest.mark.parametrize("content", ["binary", "nested", "huge"])
def test_a_recipe_that_is_not_one_is_one_line(content, tmp_path, capfd):
    path = tmp_path / "bad.toml"
    if content == "binary":
        path.write_bytes(bytes(range(256)) * 8)
    elif content == "nested":
        path.write_text("a = " + "[" * 50_000 + "]" * 50_000 + "\n")
    else:
        path.write_bytes(b"# " + b"x" * (2 << 20))
    capfd.readouterr()
    assert main(["refine", "--database", str(tmp_path / "x.db"), "--images", str(tmp_path), "--recipe", str(path),
                 "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "bad" in lines[0] and "unexpected" not in lines[0], lines


# ------------------------------------------------------------------ import
@pytest.fixture
def h5pair(scene, tmp_path):
    """features.h5 and matches.h5 (hloc layout) of the scene, exported by the CLI."""
    feats, matches = tmp_path / "features.h5", tmp_path / "matches.h5"
    assert main(["export", "--database", str(scene.database), "--features", str(feats), "--matches", str(matches),
                 "-q"]) == 0
    return feats, matches


def _import(scene, feats, matches, db) -> list[str]:
    return ["import", "--features", str(feats), "--matches", str(matches), "--images", str(scene.image_dir),
            "--database", str(db), "--no-verify", "-q"]


def _set_first_keypoints(feats, row: int, xy) -> None:
    """Set keypoint ``row`` of the first image of an h5 features file (None keeps a coordinate)."""
    import h5py

    with h5py.File(feats, "r+") as h5:
        name = next(iter(h5.keys()))
        while "keypoints" not in h5[name]:
            name = f"{name}/{next(iter(h5[name].keys()))}"
        kp = h5[name]["keypoints"][()]
        for axis, v in enumerate(xy):
            if v is not None:
                kp[row, axis] = v
        h5[name]["keypoints"][...] = kp


@pytest.mark.parametrize("value", [-500.0, 1e7, 1e30])
def test_import_refuses_keypoints_outside_the_image(value, scene, h5pair, tmp_path, capfd):
    feats, matches = h5pair
    _set_first_keypoints(feats, 3, (value, None))
    capfd.readouterr()
    assert main(_import(scene, feats, matches, tmp_path / "new.db")) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and str(feats) in lines[0] and "outside the" in lines[0] and "keypoint 3" in lines[0], lines
    assert not (tmp_path / "new.db").exists()


def test_import_accepts_keypoints_at_the_border(scene, h5pair, tmp_path):
    feats, matches = h5pair
    _set_first_keypoints(feats, 0, (-0.5, -0.5))
    assert main(_import(scene, feats, matches, tmp_path / "new.db")) == 0


def test_import_warns_about_dropped_groups_and_an_empty_matches_file(scene, h5pair, tmp_path, capfd):
    import h5py

    feats, matches = h5pair
    with h5py.File(matches, "r+") as h5:
        first = next(iter(h5.keys()))
        sub = next(iter(h5[first].keys()))
        del h5[first][sub]["matches0"]
        if "matching_scores0" not in h5[first][sub]:
            h5[first][sub].create_dataset("matching_scores0", data=[0.5])
    capfd.readouterr()
    assert main(_import(scene, feats, matches, tmp_path / "a.db")) == 0
    assert "pair group(s) without 'matches0' skipped" in capfd.readouterr().err
    empty = tmp_path / "empty.h5"
    h5py.File(empty, "w").close()
    assert main(_import(scene, feats, empty, tmp_path / "b.db")) == 0
    assert "holds no pairs: the new database has no matches" in capfd.readouterr().err


def test_import_of_an_h5_damaged_in_the_middle_is_one_line(scene, tmp_path, capfd):
    import h5py
    import numpy as np

    feats, matches = tmp_path / "f.h5", tmp_path / "m.h5"
    assert main(["export", "--database", str(scene.database), "--features", str(tmp_path / "x.h5"), "--matches",
                 str(matches), "-q"]) == 0
    with h5py.File(tmp_path / "x.h5", "r") as src, h5py.File(feats, "w") as dst:
        def copy(name, obj):
            if isinstance(obj, h5py.Dataset):
                data = obj[()]
                if name.endswith("keypoints"):
                    dst.create_dataset(name, data=data, chunks=(8, 2), compression="gzip")
                else:
                    dst.create_dataset(name, data=data)
        src.visititems(copy)
        offsets = [dst[n].id.get_chunk_info(0).byte_offset for n in [k for k in _keypoint_sets(dst)]]
    data = bytearray(feats.read_bytes())
    for off in offsets:
        data[off: off + 16] = np.random.default_rng(0).integers(0, 256, 16, dtype=np.uint8).tobytes()
    feats.write_bytes(bytes(data))
    capfd.readouterr()
    assert main(_import(scene, feats, matches, tmp_path / "new.db")) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"{feats}: cannot read the HDF5 file, damaged" in lines[0], lines
    assert not (tmp_path / "new.db").exists()


def _keypoint_sets(h5) -> list[str]:
    import h5py

    out = []
    h5.visititems(lambda n, o: out.append(n) if isinstance(o, h5py.Dataset) and n.endswith("keypoints") else None)
    return out


# ------------------------------------------------------------------ device
def _has_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


@pytest.mark.skipif(_has_cuda(), reason="the machine has a CUDA device: ncc.device=cuda is valid here")
@pytest.mark.parametrize("flags", [["--set", "ncc.device=cuda"], ["--device", "cuda"]])
def test_cuda_without_a_gpu_is_one_line_and_leaves_no_run_store(flags, db_copy, scene, tmp_path, capfd):
    out = tmp_path / "out.db"
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--workers", "1", "-q", *flags]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "cuda" in lines[0] and "no CUDA device" in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]  # no store, no working copy, no output


# ------------------------------------------------------------------ a file that is not a COLMAP database
@pytest.fixture
def other_db(tmp_path):
    import sqlite3

    path = tmp_path / "other.db"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE foo (x)")
    con.commit()
    con.close()
    return path


@pytest.mark.parametrize("command", ["map", "export", "compare", "report", "refine"])
def test_a_non_colmap_database_names_the_users_file_and_leaves_nothing(command, other_db, scene, tmp_path, capfd):
    out = tmp_path / "out" / "deeper"
    argv = {
        "map": ["map", "--database", str(other_db), "--images", str(scene.image_dir), "--output", str(out)],
        "export": ["export", "--database", str(other_db), "--features", str(tmp_path / "f.h5"), "--matches",
                   str(tmp_path / "m.h5")],
        "compare": ["compare", "--database", str(other_db), "--images", str(scene.image_dir), "--output", str(out)],
        "report": ["report", "--gt", str(tmp_path / "gt"), "--database", str(other_db)],
        "refine": ["refine", "--database", str(other_db), "--images", str(scene.image_dir), "--output",
                   str(tmp_path / "r.db")],
    }[command]
    if command == "report":
        (tmp_path / "gt").mkdir()
        scene.gt_reconstruction.write(str(tmp_path / "gt"))
    before = sorted(p.name for p in tmp_path.iterdir())
    capfd.readouterr()
    assert main([*argv, "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and lines[0].endswith(f"not a COLMAP database (missing tables: cameras, images, keypoints, "
                                                 f"matches, two_view_geometries): {other_db}"), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.parametrize("value", [-500.0, 1e7])
def test_refine_refuses_database_keypoints_outside_the_image(value, db_copy, scene, tmp_path, capfd):
    import hashlib
    import sqlite3

    import numpy as np

    con = sqlite3.connect(db_copy)
    image_id, rows, cols, data = con.execute("SELECT image_id, rows, cols, data FROM keypoints LIMIT 1").fetchone()
    kp = np.frombuffer(data, np.float32).reshape(rows, cols).copy()
    kp[5, 1] = value
    con.execute("UPDATE keypoints SET data = ? WHERE image_id = ?", (kp.tobytes(), image_id))
    con.commit()
    con.close()
    digest = hashlib.sha256(db_copy.read_bytes()).hexdigest()
    capfd.readouterr()
    assert main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                 str(tmp_path / "o.db"), "--workers", "1", "--no-refine", "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"database {db_copy}" in lines[0] and "keypoint 5 " in lines[0], lines
    assert "outside the" in lines[0] and hashlib.sha256(db_copy.read_bytes()).hexdigest() == digest
