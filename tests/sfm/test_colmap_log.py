"""COLMAP's log replayed on the terminal (``-v``, the match check's global mapper): image names
are data (a newline or ESC in one cannot forge a line), and the mapper's warning for each image
it is not given on purpose is left out."""

from __future__ import annotations

from colmap_miho.sfm.colmap_log import replay_log

LOG = (
    "Log file created at: 2026/12/06 00:41:00\n"
    "Running on machine: vm\n"
    "Running duration (h:mm:ss): 0:00:00\n"
    "Log line format: [IWEF]yyyymmdd hh:mm:ss.uuuuuu threadid file:line] msg\n"
    "I20261206 00:41:00.916939 1396 global_pipeline.cc:254] Extracting colors ...\n"
    "W20261206 00:41:00.917000 1396 reconstruction.cc:1148] Could not read image a\n"
    "I1206 FORGED\x1b[31mred.png at path \"/tmp/x/a\n"
    "I1206 FORGED\x1b[31mred.png\"\n"
    "I20261206 00:41:00.918000 1396 image.cc:10] Registered image b\n"
    "E20261206 00:41:00.918000 1396 image.cc:10] bad \x1b[2Jname\n"
)


def test_replay_escapes_names_and_leaves_out_the_per_image_warning(tmp_path, capfd):
    log = tmp_path / "colmap_log.x"
    log.write_text(LOG)
    replay_log(log)
    err = capfd.readouterr().err
    assert err.splitlines() == [
        "I20261206 00:41:00.916939 1396 global_pipeline.cc:254] Extracting colors ...",
        "I20261206 00:41:00.918000 1396 image.cc:10] Registered image b",
        "E20261206 00:41:00.918000 1396 image.cc:10] bad \\x1b[2Jname",
    ], err
    replay_log(None)
    replay_log(tmp_path / "missing")
    assert capfd.readouterr().err == ""


def test_verbose_extraction_escapes_a_name_that_needs_it(tmp_path, capfd):
    """COLMAP's extraction log names each file raw: with a name holding a newline and ESC, -v
    shows it escaped (replayed from its file), one record on one line."""
    import shutil

    from colmap_miho.sfm.extraction import extract_and_match
    from miho_bench.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(tmp_path / "scene", num_images=2, num_points=40, render_images=True, seed=5)
    images = tmp_path / "images"
    shutil.copytree(scene.image_dir, images)
    first = sorted(images.iterdir())[0]
    first.rename(images / "a\nI1206 FORGED\x1b[31mred.png")
    capfd.readouterr()
    extract_and_match(images, tmp_path / "db" / "new.db", verbose=True, max_features=200)
    err = capfd.readouterr().err
    assert "\x1b" not in err and "a\\nI1206 FORGED\\x1b[31mred.png" in err, err[-3000:]
    assert not [ln for ln in err.splitlines() if ln.startswith("I1206 FORGED")]


def test_the_mapper_steps_seconds_are_read_from_its_log(tmp_path):
    from colmap_miho.sfm.colmap_log import step_seconds

    log = tmp_path / "colmap_log.20261206-000000.1"
    log.write_text("I20261206 01:37:01.358450 140424379595648 global_mapper.cc:559] Rotation averaging done in "
                   "0.004132 seconds\nI20261206 01:37:02.391391 1404 global_mapper.cc:584] Global positioning done "
                   "in 1.02843 seconds\nI20261206 01:37:02.727974 1404 global_pipeline.cc:183] Reconstruction done in "
                   "1.37366 seconds\nI20261206 01:37:02.8 1404 x.cc:1] Some other line\n")
    assert step_seconds(log) == {"rotation averaging": 0.004132, "global positioning": 1.02843}
    assert step_seconds(None) == {} and step_seconds(tmp_path / "missing") == {}
