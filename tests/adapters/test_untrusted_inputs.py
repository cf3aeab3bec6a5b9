"""Names and values read from files are data: they never forge terminal output, and bad
values are refused up front with one line naming the option, the file or the record."""

from __future__ import annotations

from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from helpers.db_contents import sql

from colmap_miho.cli import main

FORGED = "\nERROR: forged line\x1b[31m"


def _assert_not_forged(text: str) -> None:
    assert "\x1b" not in text, text
    assert not any(line.startswith("ERROR: forged") for line in text.splitlines()), text


# ------------------------------------------------------------------ A. names are escaped
def test_a_name_with_control_characters_cannot_forge_a_line(db_copy, scene, tmp_path, capfd):
    """An image whose database name holds a newline, a forged ``ERROR:`` and an ANSI escape
    is missing from the folder: the warning and the summary name it escaped."""
    image_id, name = sql(db_copy, "SELECT image_id, name FROM images ORDER BY image_id LIMIT 1")[0]
    hostile = "é漢字" + FORGED + ".png"
    sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", hostile, image_id)
    capfd.readouterr()
    code = main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1",
                 "--output", str(tmp_path / "out.db")])
    out, err = capfd.readouterr()
    assert code == 0, err
    for text in (out, err):
        _assert_not_forged(text)
    escaped = "é漢字\\nERROR: forged line\\x1b[31m.png"
    assert any(line.startswith("WARNING: image ") and escaped in line for line in err.splitlines()), err
    assert escaped in out, out


def test_an_error_line_names_a_hostile_image_as_the_warnings_do(db_copy, scene, tmp_path, capfd):
    """``--strict`` and an image with a newline in its name missing: the error line escaped the
    name as the warnings do (it showed ``a ERROR: forged.png``, the newline a space)."""
    image_id = sql(db_copy, "SELECT image_id FROM images ORDER BY image_id LIMIT 1")[0][0]
    sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", "a" + FORGED + ".png", image_id)
    capfd.readouterr()
    code = main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1",
                 "--output", str(tmp_path / "out.db"), "--strict", "-q"])
    err = capfd.readouterr().err
    assert code == 2, err
    _assert_not_forged(err)
    line = [x for x in err.splitlines() if x.startswith("ERROR: ")][-1]
    assert "a\\nERROR: forged line\\x1b[31m.png is missing" in line, line


def test_printable_keeps_names_readable_and_escapes_controls():
    from colmap_miho.terminal import printable

    assert printable("façade_漢字.jpg") == "façade_漢字.jpg"
    assert printable("a\r\n\t\x00\x7f\x85\x9b\u202eb") == "a\\r\\n\\t\\x00\\x7f\\x85\\x9b\\u202eb"
    assert printable("x\ny", keep_newlines=True) == "x\ny"
    # the bidirectional marks reorder text as the overrides do
    assert printable("a\u200fb\u200ec\u061cd") == "a\\u200fb\\u200ec\\u061cd"


# ------------------------------------------------------------------ B. camera parameters
@pytest.mark.parametrize("params, shown", [("0,0,320,240", "focal length 0 "), ("1e308,1e308,320,240", "1e+308"),
                                           ("700,-5,320,240", "focal length -5 "),
                                           ("2e9,700,320,240", "focal length 2e+09")])
def test_a_meaningless_focal_length_is_refused_up_front(params, shown, db_copy, scene, tmp_path, capfd):
    out = tmp_path / "m"
    capfd.readouterr()
    code = main(["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                 "--camera-model", "PINHOLE", "--camera-params", params, "-q"])
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, lines
    assert "camera_params: " in lines[0] and shown in lines[0] and "must be > 0" in lines[0], lines
    assert not out.exists()


def test_ordinary_camera_parameters_are_kept():
    from colmap_miho.sfm import parse_camera_params

    assert parse_camera_params("PINHOLE", "1379.7,1382.1,760.8,503.9") == (1379.7, 1382.1, 760.8, 503.9)
    assert parse_camera_params("SIMPLE_RADIAL", "1e6,0,0,-0.3") == (1e6, 0.0, 0.0, -0.3)


# ------------------------------------------------------------------ C. missing camera rows
@pytest.mark.parametrize("command", ["refine", "map"])
def test_a_missing_camera_row_is_named_not_blamed_on_the_images(command, db_copy, scene, tmp_path, capfd):
    """Images 2 and 3 refer to camera 7, which has no row: refine saw a 0x0 camera and blamed
    every image file; map failed on an unknown camera (exit 1)."""
    sql(db_copy, "UPDATE images SET camera_id = 7 WHERE image_id IN (2, 3)")
    names = [r[0] for r in sql(db_copy, "SELECT name FROM images WHERE image_id IN (2, 3) ORDER BY image_id")]
    argv = {"refine": ["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1",
                       "--output", str(tmp_path / "out.db"), "-q"],
            "map": ["map", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                    str(tmp_path / "m"), "-q"]}[command]
    capfd.readouterr()
    assert main(argv) == 2
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert f"database {db_copy} is damaged: the cameras table has no row for camera 7 (used by 2 image(s): " \
           f"{names[0]!r}, {names[1]!r})" in lines[0], lines


# ------------------------------------------------------------------ D. compare creates nothing on bad input
def test_compare_with_a_missing_image_folder_creates_no_folder(db_copy, tmp_path, capfd):
    out = tmp_path / "cmp" / "out"
    capfd.readouterr()
    code = main(["compare", "--database", str(db_copy), "--images", str(tmp_path / "no_images"), "--output",
                 str(out), "-q"])
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and lines == [f"ERROR: image folder not found: {tmp_path / 'no_images'}"], lines
    assert not (tmp_path / "cmp").exists()


# ------------------------------------------------------------------ hloc h5 files (E, F, G)
@pytest.fixture()
def tiny(tmp_path):
    """Two 64x48 images in a sub-folder, three keypoints each, hloc's nested matches layout."""
    img = tmp_path / "imgs"
    (img / "sub").mkdir(parents=True)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(img / "sub" / name), np.zeros((48, 64), np.uint8))
    f, m = tmp_path / "f.h5", tmp_path / "m.h5"
    with h5py.File(f, "w") as h:
        h.create_dataset("sub/a.png/keypoints", data=np.array([[10.0, 20.0], [0.0, 0.0], [63.0, 47.0]]))
        h.create_dataset("sub/b.png/keypoints", data=np.array([[11.0, 21.0], [1.0, 1.0], [62.0, 46.0]]))
    with h5py.File(m, "w") as h:
        h.create_dataset("sub-a.png/sub-b.png/matches0", data=np.array([0, -1, 2]))
    return f, m, img, tmp_path


def _import(f, m, img, db, *extra) -> list[str]:
    return ["import", "-q", "--features", str(f), "--matches", str(m), "--images", str(img), "--database", str(db),
            "--no-verify", *extra]


def _one_error(capfd, argv, code: int = 2) -> str:
    capfd.readouterr()
    assert main(argv) == code
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    return lines[0]


def test_import_never_advises_an_option_it_does_not_have(tiny, monkeypatch, capfd):
    """The new database appears (another run) while import works: the refusal must name what
    ``import`` offers, not ``--overwrite`` (which it has not)."""
    from colmap_miho.adapters import exchange
    from colmap_miho.cli import build_parser

    f, m, img, tmp = tiny
    db = tmp / "new.db"
    real = exchange.check_integrity

    def other_run_writes(*args, **kwargs):
        real(*args, **kwargs)
        db.write_bytes(b"another run's database")

    monkeypatch.setattr(exchange, "check_integrity", other_run_writes)
    line = _one_error(capfd, _import(f, m, img, db))
    assert f"output {db} was created by another program during the run" in line, line
    assert "--overwrite" not in line and "choose another --database" in line, line
    assert db.read_bytes() == b"another run's database"
    import_options = build_parser()._subparsers._group_actions[0].choices["import"]._option_string_actions
    assert "--database" in import_options and "--overwrite" not in import_options


def _replace_b(f: Path, make) -> None:
    with h5py.File(f, "a") as h:
        del h["sub/b.png"]
        make(h)


@pytest.mark.parametrize("make, expected", [
    (lambda h: h.create_dataset("sub/b.png/keypoints/xy", data=np.zeros((3, 2))),
     "'keypoints' of image 'sub/b.png' is a group, expected an (N, 2) dataset"),
    (lambda h: h.create_dataset("sub/b.png/descriptors", data=np.zeros((256, 3), np.float32)),
     "image 'sub/b.png' has no 'keypoints' dataset (it holds descriptors)"),
], ids=["keypoints-group", "keypoints-missing"])
def test_broken_keypoints_are_named_not_reported_as_a_missing_image(make, expected, tiny, capfd):
    f, m, img, tmp = tiny
    _replace_b(f, make)
    line = _one_error(capfd, _import(f, m, img, tmp / "bad.db"))
    assert f"ERROR: {f}: {expected}" == line, line
    assert not list(tmp.glob("bad.db*"))


def _matches0(m: Path, values, dtype) -> None:
    with h5py.File(m, "a") as h:
        del h["sub-a.png/sub-b.png/matches0"]
        h.create_dataset("sub-a.png/sub-b.png/matches0", data=np.array(values, dtype))


def test_uint64_matches0_is_converted_with_a_range_check_and_no_warning(tiny, capfd):
    import warnings

    f, m, img, tmp = tiny
    _matches0(m, [0, 2**64 - 1, 2], np.uint64)  # a -1 written as uint64
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy cast warning would fail the import (exit 1)
        line = _one_error(capfd, _import(f, m, img, tmp / "bad.db"))
    assert line == (f"ERROR: pair ('sub/a.png', 'sub/b.png'): 'matches0': keypoint index {2**64 - 1} out of range in "
                    "entry 1 (images have 3 and 3 keypoints; an unsigned array cannot hold -1 for 'unmatched')"), line
    _matches0(m, [2, 0, 1], np.uint64)  # in range: imported as is
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(_import(f, m, img, tmp / "ok.db")) == 0
    pairs = sql(tmp / "ok.db", "SELECT rows FROM matches")
    assert pairs == [(3,)]


# ------------------------------------------------------------------ H. SIGTERM during a slow clean-up
SLOW_CLEANUP = """
import sys, time
from pathlib import Path
import colmap_miho.cli as cli
import colmap_miho.commands.map as cmd
from colmap_miho.errors import Terminated

cli.TERM_GRACE_S = 0.5  # the clean-up below takes longer than the grace, like a Dask cluster's shutdown

def run(args):
    Path(sys.argv[1]).write_text("running")
    try:
        while True:
            time.sleep(0.01)  # Python code: the SIGTERM handler is served at once
    except Terminated:
        time.sleep(2.0)
        raise

cmd.run = run
sys.exit(cli.main(["map", "--database", sys.argv[2], "--images", sys.argv[3], "--output", sys.argv[4], "-q"]))
"""


def test_sigterm_served_during_a_slow_clean_up_is_one_line_not_blamed_on_colmap(db_copy, scene, tmp_path):
    """With ``--dask`` the cluster's shutdown after a SIGTERM took longer than the watcher's
    grace: it then printed a second line blaming "a COLMAP call" and cut the clean-up short."""
    import os
    import signal
    import subprocess
    import sys
    import time

    marker = tmp_path / "marker"
    script = tmp_path / "slow_cleanup.py"
    script.write_text(SLOW_CLEANUP)
    proc = subprocess.Popen([sys.executable, str(script), str(marker), str(db_copy), str(scene.image_dir),
                             str(tmp_path / "m")], stderr=subprocess.PIPE, text=True, env=os.environ.copy())
    try:
        deadline = time.monotonic() + 120
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert marker.exists(), proc.stderr.read() if proc.poll() is not None else "not started in time"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = [line for line in err.splitlines() if line.strip()]
    assert proc.returncode == 143 and len(lines) == 1, lines
    assert lines[0].startswith("ERROR: terminated (SIGTERM); working files removed") and "COLMAP" not in lines[0]


# ------------------------------------------------------------------ I. long names in figures
@pytest.mark.parametrize("num_pairs, name", [
    (60, lambda i: f"{i}_" + "very_long_folder_name/" * 12 + f"image_{i}.png"),
    (3, lambda i: f"{i}" + "x" * 300 + "\nERROR\x1b[31m.png"),
])
def test_long_image_names_make_no_layout_warning(num_pairs, name, tmp_path):
    import warnings

    pytest.importorskip("matplotlib")
    from colmap_miho.reporting import plots

    before = {f"{name(i)}|{name(i + 1)}": 100 + i for i in range(num_pairs)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # matplotlib's "Tight layout not applied" was shown to the user
        path = plots.plot_matches_per_pair(before, {k: v // 2 for k, v in before.items()}, tmp_path / "m.png")
    assert path.stat().st_size > 0
    labels = plots.short_labels(list(before))
    assert all(len(lab) <= 2 * plots.MAX_NAME_CHARS + 1 and "\n" not in lab and "\x1b" not in lab for lab in labels)
    assert len(set(labels)) == len(labels)  # still tells the pairs apart


def test_matches_per_pair_axis_labels_are_plain_numbers(tmp_path, monkeypatch):
    """Under plain_text (no math text) the log axis' default labels showed raw TeX."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from colmap_miho.reporting import plots

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to read its labels
    before = {f"a{i}.png|b{i}.png": 60 + 20 * i for i in range(3)}
    plots.plot_matches_per_pair(before, before, tmp_path / "m.png")
    ax = figures[0].axes[0]
    texts = [t.get_text() for t in ax.get_yticklabels() + ax.get_yticklabels(minor=True) if t.get_text()]
    assert texts and not any("$" in t or "mathdefault" in t for t in texts), texts
