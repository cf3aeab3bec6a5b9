"""Test runner: ``python hold_at_write.py MARKER RESUME CLI_ARGS...`` runs ``colmap-miho
CLI_ARGS``; once one pair is written it creates MARKER and waits until RESUME exists, then
finishes the run: ``test_reliability`` acts meanwhile (another run, another program) to test the
checks repeated at commit time."""

import sys
import time
from pathlib import Path

from write_hook import run_with_write_hook

#: Longest wait for RESUME; the test resumes long before, this only bounds a forgotten runner.
HOLD_S = 120


def _hold() -> None:
    Path(sys.argv[1]).write_text("write")
    deadline = time.monotonic() + HOLD_S
    while not Path(sys.argv[2]).exists() and time.monotonic() < deadline:
        time.sleep(0.05)


if __name__ == "__main__":
    sys.exit(run_with_write_hook(_hold, sys.argv[3:]))
