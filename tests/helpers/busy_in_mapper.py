"""Test runner: ``python busy_in_mapper.py MARKER CLI_ARGS...`` runs ``colmap-miho CLI_ARGS``
with pycolmap's global mapper replaced by one long C call that never returns to the interpreter
(as the real mapper holds it for 10-30 s on a real scene); MARKER is created when it starts, so
that the test sends its signal while the interpreter is held. With ``MIHO_TEST_POOL`` set, the
filter runs in worker processes even on a tiny scene."""

import hashlib
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's colmap_miho

import pycolmap  # noqa: E402

from colmap_miho.cli import main  # noqa: E402

#: PBKDF2 rounds of the held call: tens of seconds on any CPU (the test's signal comes at once).
ROUNDS = 200_000_000


def _busy(*args, **kwargs):
    Path(sys.argv[1]).write_text("mapper")
    hashlib.pbkdf2_hmac("sha256", b"held", b"salt", ROUNDS)
    return {}


if __name__ == "__main__":
    pycolmap.global_mapping = _busy
    if os.environ.get("MIHO_TEST_POOL"):  # filter in worker processes even on a tiny scene
        from colmap_miho.pipeline import filter as filter_stage

        filter_stage.MIN_PAIRS_PER_WORKER = filter_stage.MIN_MATCHES_PER_FILTER_WORKER = 0
    sys.exit(main(sys.argv[2:]))
