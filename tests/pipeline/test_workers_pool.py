"""The worker pool: forked by the forkserver (which imported torch once), spawn when the
forkserver cannot start."""

from __future__ import annotations

import math
import multiprocessing
import os

import pytest

from colmap_miho.pipeline import workers

pytestmark = pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(),
                                reason="no forkserver on this platform")


def test_workers_come_from_the_forkserver():
    with workers.process_pool(2) as ex:
        assert ex._mp_context.get_start_method() == "forkserver"
        ppids = {ex.submit(os.getppid).result(timeout=120) for _ in range(4)}
    assert os.getpid() not in ppids  # their parent is the server, not this process


def test_pool_falls_back_to_spawn_when_the_forkserver_cannot_start(monkeypatch):
    from multiprocessing import forkserver

    def broken():
        raise OSError("no writable temporary folder")

    monkeypatch.setattr(workers, "_FORKSERVER_FAILED", [])
    monkeypatch.setattr(forkserver, "ensure_running", broken)
    with workers.process_pool(1) as ex:
        assert ex._mp_context.get_start_method() == "spawn"
        assert ex.submit(math.sqrt, 16.0).result(timeout=120) == 4.0
        assert ex.submit(os.getppid).result(timeout=120) == os.getpid()
    assert workers._FORKSERVER_FAILED == ["no writable temporary folder"]
