"""Test runner: ``python busy_at_write.py MARKER CLI_ARGS...`` runs ``colmap-miho CLI_ARGS``;
once one pair is written it enters a long computation in C that never returns to the
interpreter (like a long COLMAP call), after creating MARKER: ``test_reliability`` sends SIGTERM
there, which Python's own handler cannot serve in time."""

import hashlib
import sys
import threading
from pathlib import Path

from write_hook import run_with_write_hook

#: PBKDF2 rounds: far longer than the test waits (minutes), all inside one C call.
ROUNDS = 10**9
#: Seconds between entering the C call and writing the marker.
MARKER_DELAY_S = 1.0


def _busy() -> None:
    # the marker is written by a thread once this thread is inside the C call (which releases
    # the GIL): a SIGTERM sent before it would be served by Python's handler
    threading.Timer(MARKER_DELAY_S, Path(sys.argv[1]).write_text, args=("write",)).start()
    hashlib.pbkdf2_hmac("sha256", b"colmap", b"miho", ROUNDS)


if __name__ == "__main__":
    sys.exit(run_with_write_hook(_busy, sys.argv[2:]))
