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
