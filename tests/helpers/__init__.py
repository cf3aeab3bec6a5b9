"""Test helpers: scripts that run ``colmap-miho`` and stop in its write stage
(``*_at_write.py``, started as subprocesses), and :func:`start_at_write` to start them."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

HELPERS = Path(__file__).resolve().parent
REPO = HELPERS.parents[1]
#: Seconds a subprocess may take to reach the write stage (imports torch, filters the pairs).
REACH_WRITE_TIMEOUT_S = 120


def start_at_write(script: str, marker: Path, *args: str, ignored: tuple[int, ...] = ()) -> subprocess.Popen:
    """Start ``tests/helpers/<script>`` with ``marker`` and ``args`` and wait until it has
    written ``marker`` (it is then inside the write stage). Fails the test when the process
    ends first or does not get there within ``REACH_WRITE_TIMEOUT_S``; the caller owns the
    returned process (text-mode stderr pipe). ``ignored``: signals the process starts with
    ignored (as under ``nohup``, or a shell's background job)."""
    import signal

    def ignore() -> None:
        for sig in ignored:
            signal.signal(sig, signal.SIG_IGN)

    cmd = [sys.executable, str(HELPERS / script), str(marker), *args]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=ignore if ignored else None)
    deadline = time.monotonic() + REACH_WRITE_TIMEOUT_S
    while not marker.exists():
        if proc.poll() is not None:
            pytest.fail(f"refine ended before the write stage: {proc.stderr.read() if proc.stderr else ''}")
        if time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            pytest.fail("refine did not reach the write stage in time")
        time.sleep(0.05)
    return proc
