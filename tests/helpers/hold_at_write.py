"""Test runner: ``python hold_at_write.py MARKER RESUME CLI_ARGS...`` runs ``colmap-miho
CLI_ARGS`` with the write stage's per-pair call wrapped so that, once one pair is written, it
creates MARKER and waits until RESUME exists, then finishes the run: ``test_reliability`` acts
meanwhile (another run, another program) to test the checks repeated at commit time."""

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's colmap_miho

import colmap_miho.pipeline.write as write_stage
from colmap_miho.cli import main

#: Longest wait for RESUME; the test resumes long before, this only bounds a forgotten runner.
HOLD_S = 120


def _holding(write_pair):
    calls = 0

    def wrapped(*args, **kwargs):
        nonlocal calls
        calls += 1
        if calls == 2:  # one pair is in the open transaction
            Path(sys.argv[1]).write_text("write")
            deadline = time.monotonic() + HOLD_S
            while not Path(sys.argv[2]).exists() and time.monotonic() < deadline:
                time.sleep(0.05)
        return write_pair(*args, **kwargs)

    return wrapped


if __name__ == "__main__":
    write_stage.write_pair = _holding(write_stage.write_pair)
    sys.exit(main(sys.argv[3:]))
