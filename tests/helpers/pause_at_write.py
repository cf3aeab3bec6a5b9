"""Test runner: ``python pause_at_write.py MARKER CLI_ARGS...`` runs ``colmap-miho CLI_ARGS``
with the write stage paused once one pair is written: it creates MARKER and sleeps, and
``test_safety`` kills the process in the middle of writing."""

import sys
import time
from pathlib import Path

from write_hook import run_with_write_hook

#: The process is killed long before this; the sleep only bounds a forgotten runner.
PAUSE_S = 60


def _pause() -> None:
    Path(sys.argv[1]).write_text("write")
    time.sleep(PAUSE_S)


if __name__ == "__main__":
    sys.exit(run_with_write_hook(_pause, sys.argv[2:]))
