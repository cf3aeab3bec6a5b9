"""Test runner: ``python pause_at_write.py MARKER CLI_ARGS...`` runs ``colmap-miho CLI_ARGS``
with the write stage's per-pair call wrapped so that, once one pair is written, it creates
MARKER and sleeps: ``test_safety`` then kills the process in the middle of writing."""

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's colmap_miho

import colmap_miho.pipeline.write as write_stage
from colmap_miho.cli import main

#: The process is killed long before this; the sleep only bounds a forgotten runner.
PAUSE_S = 60


def _pausing(write_pair):
    calls = 0

    def wrapped(*args, **kwargs):
        nonlocal calls
        calls += 1
        if calls == 2:  # one pair is in the open transaction
            Path(sys.argv[1]).write_text("write")
            time.sleep(PAUSE_S)
        return write_pair(*args, **kwargs)

    return wrapped


if __name__ == "__main__":
    write_stage.write_pair = _pausing(write_stage.write_pair)
    sys.exit(main(sys.argv[2:]))
