"""Known bad data is a one-line error naming the file and the image or pair (or a warning),
never a crash or a silent change of the result."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from helpers.db_contents import sql

from colmap_miho.adapters.paths import leaves_folder
from colmap_miho.cli import main


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip() and line.startswith("ERROR")]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _refine(db: Path, images: Path, *extra: str) -> list[str]:
    return ["refine", "--database", str(db), "--images", str(images), "--workers", "1", "--no-refine", *extra, "-q"]


def test_nan_keypoints_name_the_image(db_copy, scene, capfd):
    image_id, rows, cols, data = sql(db_copy, "SELECT image_id, rows, cols, data FROM keypoints LIMIT 1")[0]
    kp = np.frombuffer(data, np.float32).reshape(rows, cols).copy()
    kp[3, 1] = np.nan
    sql(db_copy, "UPDATE keypoints SET data = ? WHERE image_id = ?", kp.tobytes(), image_id)
    name = sql(db_copy, "SELECT name FROM images WHERE image_id = ?", image_id)[0][0]
    digest = sha256(db_copy)
    capfd.readouterr()
    assert main(_refine(db_copy, scene.image_dir)) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"keypoints of image {name!r} (id {image_id}) contain NaN or inf" in lines[0], lines
    assert str(db_copy) in lines[0] and sha256(db_copy) == digest


@pytest.mark.parametrize("command", ["refine", "map", "export"])
def test_a_lying_blob_size_is_one_line(command, db_copy, scene, tmp_path, capfd):
    """``keypoints.rows`` far beyond the blob: pycolmap would ask for terabytes (bad_alloc)."""
    image_id = sql(db_copy, "SELECT image_id FROM keypoints LIMIT 1")[0][0]
    sql(db_copy, "UPDATE keypoints SET rows = 4000000000000 WHERE image_id = ?", image_id)
    argv = {"refine": _refine(db_copy, scene.image_dir),
            "map": ["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                    str(tmp_path / "m"), "-q"],
            "export": ["export", "--database", str(db_copy), "--features", str(tmp_path / "f.h5"), "--matches",
                       str(tmp_path / "m.h5"), "-q"]}[command]
    capfd.readouterr()
    assert main(argv) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1, lines
    assert f"database {db_copy} is damaged: keypoints of image {image_id} says 4000000000000 x" in lines[0], lines


def test_repeated_match_rows_are_counted_once(db_copy, scene, tmp_path, capfd):
    pair_id, rows, data = sql(db_copy, "SELECT pair_id, rows, data FROM two_view_geometries WHERE rows > 20 "
                                        "LIMIT 1")[0]
    m = np.frombuffer(data, np.uint32).reshape(rows, 2)
    doubled = np.concatenate([m, m[:7]])
    sql(db_copy, "UPDATE two_view_geometries SET rows = ?, data = ? WHERE pair_id = ?", len(doubled),
         doubled.tobytes(), pair_id)
    out = tmp_path / "out.db"
    capfd.readouterr()
    assert main(_refine(db_copy, scene.image_dir, "--output", str(out))[:-1]) == 0  # without -q: INFO shown
    assert "7 repeated rows in its verified matches, counted once" in capfd.readouterr().err
    rows_out, data_out = sql(out, "SELECT rows, data FROM two_view_geometries WHERE pair_id = ?", pair_id)[0]
    kept = np.frombuffer(data_out, np.uint32).reshape(rows_out, 2)
    assert len(np.unique(kept, axis=0)) == len(kept) <= len(m)


def test_leaves_folder():
    assert not leaves_folder("a.png") and not leaves_folder("sub/../a.png") and not leaves_folder("./x/y.jpg")
    assert leaves_folder("../a.png") and leaves_folder("/etc/passwd") and leaves_folder("sub/../../a.png")
    assert leaves_folder("") and leaves_folder("..\\a.png")


def test_image_named_outside_the_folder_is_skipped_or_refused(db_copy, scene, tmp_path, capfd):
    """A database name ``../<folder>/<image>`` would read the image from beside --images: a
    warning and the image skipped; an error with --strict."""
    image_id, name = sql(db_copy, "SELECT image_id, name FROM images LIMIT 1")[0]
    outside = f"../{scene.image_dir.name}/{name}"
    sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", outside, image_id)
    refine = ["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1", "-q"]
    capfd.readouterr()
    assert main([*refine, "--output", str(tmp_path / "a.db")]) == 0
    err = capfd.readouterr().err
    assert "named outside the image folder" in err and "it is skipped" in err, err
    assert main([*refine, "--output", str(tmp_path / "b.db"), "--strict"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "named outside the image folder" in lines[0] and "--strict" in lines[0], lines


def test_import_refuses_an_image_named_outside_the_folder(scene, tmp_path, capfd):
    import h5py

    feats, matches = tmp_path / "f.h5", tmp_path / "m.h5"
    assert main(["export", "--database", str(scene.database), "--features", str(feats), "--matches",
                 str(matches), "--layout", "dim", "-q"]) == 0
    with h5py.File(feats, "r+") as fh:
        first = next(iter(fh))
        fh.move(first, f"../{first}")
    capfd.readouterr()
    code = main(["import", "--features", str(feats), "--matches", str(matches), "--images", str(scene.image_dir),
                 "--database", str(tmp_path / "new.db"), "-q"])
    lines = error_lines(capfd.readouterr().err)
    assert code == 2 and len(lines) == 1 and "named outside the image folder" in lines[0], lines
    assert not (tmp_path / "new.db").exists()


def test_map_warns_about_image_names_outside_the_folder(db_copy, scene, tmp_path, capfd):
    image_id, name = sql(db_copy, "SELECT image_id, name FROM images LIMIT 1")[0]
    sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", f"../{scene.image_dir.name}/{name}", image_id)
    capfd.readouterr()
    main(["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(tmp_path / "m")])
    assert "1 image name(s) of" in capfd.readouterr().err


@pytest.mark.parametrize(("damage", "message"), [
    ("DELETE FROM frame_data WHERE data_id = (SELECT min(image_id) FROM images)",
     "1 image(s) with no row in frame_data"),
    ("DELETE FROM frames", "image(s) with a frame with no row in frames"),
    ("DELETE FROM rigs", "image(s) with a frame whose rig has no row in rigs"),
    ("UPDATE frame_data SET sensor_id = 77 WHERE data_id = (SELECT max(image_id) FROM images)",
     "1 image(s) with a frame_data row naming another camera"),
    ("UPDATE cameras SET model = 99", "has model id 99, which is no COLMAP camera model"),
    ("UPDATE cameras SET params = x'00'", "holds 1 bytes of parameters"),
])
@pytest.mark.parametrize("command", ["refine", "map"])
def test_damaged_rig_frame_or_camera_rows_name_the_database(command, damage, message, db_copy, scene, tmp_path,
                                                            capfd):
    """pycolmap says ``Check failed: frame.HasDataId(image.DataId())`` or ``Camera model does
    not exist`` (an "unexpected" error): one line naming the database and what is damaged."""
    sql(db_copy, damage)
    digest = sha256(db_copy)
    argv = {"refine": _refine(db_copy, scene.image_dir, "--output", str(tmp_path / "o.db")),
            "map": ["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                    str(tmp_path / "m"), "-q"]}[command]
    capfd.readouterr()
    assert main(argv) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"database {db_copy} is damaged: " in lines[0] and message in lines[0], lines
    assert sha256(db_copy) == digest and not (tmp_path / "o.db").exists() and not (tmp_path / "m").exists()


@pytest.mark.parametrize("alias", ["./{}", ".//{}", "link.png"])
def test_two_rows_naming_one_file_are_named(alias, db_copy, scene, tmp_path, capfd):
    """``./a.png`` beside ``a.png`` (or a link to it): the second row's keypoints would be
    refined against the first one's pixels without a word. A warning naming both rows; an error
    with --strict."""
    import shutil

    images = tmp_path / "images"
    shutil.copytree(scene.image_dir, images)
    (first, name), (second, _) = sql(db_copy, "SELECT image_id, name FROM images ORDER BY image_id LIMIT 2")
    if alias == "link.png":
        (images / alias).symlink_to(images / name)
    sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", alias.format(name), second)
    refine = ["refine", "--database", str(db_copy), "--images", str(images), "--workers", "1", "-q"]
    capfd.readouterr()
    assert main([*refine, "--output", str(tmp_path / "a.db")]) == 0
    err = capfd.readouterr().err
    assert f"{name!r} (id {first}) and {alias.format(name)!r} (id {second})" in err and "same pixels" in err, err
    assert main([*refine, "--output", str(tmp_path / "b.db"), "--strict"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "name a file that another row names already" in lines[0], lines
    assert str(db_copy) in lines[0] and "--strict" in lines[0] and not (tmp_path / "b.db").exists()


@pytest.mark.parametrize("command", ["import", "refine"])
def test_a_dangling_symlink_output_is_named_as_such(command, db_copy, scene, tmp_path, capfd):
    """An output name that is a link to nothing existed before the run: not "created by
    another program during the run" after the work, but one line before it."""
    link = tmp_path / "link.db"
    link.symlink_to(tmp_path / "gone.db")
    if command == "import":
        feats, matches = tmp_path / "f.h5", tmp_path / "m.h5"
        assert main(["export", "--database", str(db_copy), "--features", str(feats), "--matches", str(matches),
                     "-q"]) == 0
        argv = ["import", "--features", str(feats), "--matches", str(matches), "--images", str(scene.image_dir),
                "--database", str(link), "-q"]
    else:
        argv = _refine(db_copy, scene.image_dir, "--output", str(link))
    capfd.readouterr()
    assert main(argv) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and f"{link} is a symlink to {tmp_path / 'gone.db'}, which does not exist" in lines[0], lines
    assert "during the run" not in lines[0] and link.is_symlink() and not (tmp_path / "gone.db").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".link.db")]


def test_the_match_check_never_asks_for_more_threads_than_cores(db_copy, scene, tmp_path, monkeypatch):
    """``workers`` (up to 1024, or a remote Dask cluster's slots) sizes the pool; the global
    mapper runs here and gets at most this machine's cores."""
    from colmap_miho import refine_database
    from colmap_miho.pipeline import refine_job as run_module

    asked: list[int] = []

    def spy(*args, threads, **kwargs):
        asked.append(threads)
        raise KeyboardInterrupt  # enough: stop the run here

    monkeypatch.setattr(run_module, "run_match_check", spy)
    monkeypatch.setattr(run_module.os, "cpu_count", lambda: 2)
    with pytest.raises(KeyboardInterrupt):
        refine_database(db_copy, scene.image_dir, tmp_path / "o.db", workers=64, restart=True)
    assert asked == [2]


def test_verbose_map_shows_no_raw_name(db_copy, scene, tmp_path, capfd):
    """``map -v`` with an image name holding a newline and ESC, its file missing: COLMAP's log
    names it raw ("Could not read image ..."); replayed escaped, nothing forges a line or
    recolours the terminal."""
    images = scene.image_dir
    image_id = sql(db_copy, "SELECT image_id FROM images ORDER BY image_id LIMIT 1")[0][0]
    evil = "a\nERROR: forged\x1b[31m.png"
    sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", evil, image_id)
    capfd.readouterr()
    assert main(["map", "--database", str(db_copy), "--images", str(images), "--output", str(tmp_path / "m"),
                 "-v"]) == 0
    err = capfd.readouterr().err
    assert "\x1b" not in err and not [ln for ln in err.splitlines() if ln.startswith("ERROR: forged")], err[-2000:]
