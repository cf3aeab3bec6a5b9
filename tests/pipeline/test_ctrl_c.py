"""Ctrl-C sends SIGINT to every process of the terminal's foreground group: the worker
processes and the forkserver (while it imports torch) must not print their own tracebacks;
the parent prints one line (the CLI: exit 130)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from helpers import REPO

pytestmark = pytest.mark.skipif(not hasattr(signal, "pthread_sigmask") or not os.path.isdir("/proc"),
                                reason="needs POSIX signal masks and /proc")

SCRIPT = textwrap.dedent("""
    import sys, time
    from colmap_miho.pipeline.workers import process_pool, start_forkserver
    try:
        start_forkserver()  # the forkserver now imports torch in the background
        print("ready", flush=True)
        if sys.argv[1] == "pool":
            with process_pool(2) as ex:
                [f.result() for f in [ex.submit(time.sleep, 0.2) for _ in range(4)]]  # both workers up
                print("pool ready", flush=True)
                futures = [ex.submit(time.sleep, 30) for _ in range(2)]
                [f.result() for f in futures]
        else:
            time.sleep(30)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
""")


def _blocked_signals(pid: int) -> int:
    with open(f"/proc/{pid}/status") as fh:
        return int(next(line for line in fh if line.startswith("SigBlk")).split()[1], 16)


@pytest.mark.parametrize("what", ["forkserver", "pool"])
def test_ctrl_c_prints_one_line_not_the_workers_tracebacks(what):
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, what], cwd=REPO, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.stdout.readline().strip() == "ready"
    if what == "pool":
        assert proc.stdout.readline().strip() == "pool ready"
    time.sleep(0.5)  # the forkserver mid-import of torch / the workers busy
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130
    assert err.strip().splitlines() == ["interrupted"], err


def test_processes_started_in_the_block_never_get_sigint():
    from colmap_miho.pipeline.workers import sigint_for_this_process_only

    with sigint_for_this_process_only():
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(5)"])
    try:
        assert _blocked_signals(child.pid) & (1 << (signal.SIGINT - 1))
        assert not _blocked_signals(os.getpid()) & (1 << (signal.SIGINT - 1))
    finally:
        child.kill()
        child.wait()
