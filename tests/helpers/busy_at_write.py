"""Test runner: ``python busy_at_write.py MARKER CLI_ARGS...`` runs ``colmap-miho CLI_ARGS``
with the write stage's per-pair call replaced, after one pair, by a long computation in C that
never returns to the interpreter (like a long COLMAP call), after creating MARKER:
``test_reliability`` sends SIGTERM there, which Python's own handler cannot serve in time."""

import hashlib
import sys
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's colmap_miho

import colmap_miho.pipeline.write as write_stage
from colmap_miho.cli import main

#: PBKDF2 rounds: far longer than the test waits (minutes), all inside one C call.
ROUNDS = 10**9
#: Seconds between entering the C call and writing the marker.
MARKER_DELAY_S = 1.0


def _busy(write_pair):
    calls = 0

    def wrapped(*args, **kwargs):
        nonlocal calls
        calls += 1
        if calls == 2:
            # the marker is written by a thread once this thread is inside the C call (which
            # releases the GIL): a SIGTERM sent before it would be served by Python's handler
            threading.Timer(MARKER_DELAY_S, Path(sys.argv[1]).write_text, args=("write",)).start()
            hashlib.pbkdf2_hmac("sha256", b"colmap", b"miho", ROUNDS)
        return write_pair(*args, **kwargs)

    return wrapped


if __name__ == "__main__":
    write_stage.write_pair = _busy(write_stage.write_pair)
    sys.exit(main(sys.argv[2:]))
