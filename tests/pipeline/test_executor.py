"""The pipeline's engines: in-process, process pool and a local Dask cluster give the same
results, a task's error reaches the caller, and a bad scheduler address is one clear error."""

from __future__ import annotations

import os
import time
from concurrent.futures import Future

import numpy as np
import pytest

from colmap_miho.errors import UserError
from colmap_miho.pipeline.executor import LOCAL, Runner, open_runner


def square_sum(seed: int, n: int) -> tuple[int, float, int]:
    """A task: a seeded computation, and the worker's pid."""
    x = np.random.default_rng(seed).normal(size=n)
    return seed, float((x * x).sum()), os.getpid()


def fail(message: str) -> None:
    raise ValueError(message)


def torch_threads() -> int:
    import torch

    return torch.get_num_threads()


def _run(runner) -> dict[int, float]:
    futs = [runner.submit(square_sum, s, 1000) for s in range(6)]
    return {s: v for s, v, _ in (f.result() for f in futs)}


def test_inline_runner_calls_in_this_process():
    with open_runner(1) as runner:
        assert runner.kind == "inline" and runner.slots == 1 and not runner.parallel
        _, _, pid = runner.submit(square_sum, 0, 10).result()
        assert pid == os.getpid()
        with pytest.raises(ValueError, match="boom"):
            runner.submit(fail, "boom").result()


@pytest.mark.parametrize("dask", [None, LOCAL])
def test_engines_agree_and_use_other_processes(dask):
    with open_runner(1) as inline:
        expected = _run(inline)
    with open_runner(2, dask) as runner:
        assert runner.parallel and runner.slots == 2
        assert runner.kind == ("dask" if dask else "processes")
        assert _run(runner) == expected
        pids = {runner.submit(square_sum, s, 10).result()[2] for s in range(4)}
        assert os.getpid() not in pids
        assert runner.submit(torch_threads).result() == 1  # one thread per task
        with pytest.raises(ValueError, match="boom"):
            runner.submit(fail, "boom").result()


def test_unreachable_scheduler_is_one_clear_error(monkeypatch):
    monkeypatch.setattr("colmap_miho.pipeline.executor.CONNECT_TIMEOUT_S", 2)
    with pytest.raises(UserError, match="cannot reach the Dask scheduler"), \
            open_runner(2, "tcp://127.0.0.1:1"):
        pass
    with pytest.raises(UserError, match="scheduler address"), open_runner(2, "myhost:8786"):
        pass


def test_a_pool_starts_in_the_background():
    with open_runner(1) as inline:
        assert inline.start_in_background()() is False  # nothing to start
    with open_runner(2) as runner:
        starting = runner.start_in_background()
        deadline = time.monotonic() + 120
        while starting() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not starting() and runner.started
        assert runner.start_in_background()() is False  # started already
        assert runner.submit(square_sum, 1, 10).result()[2] != os.getpid()


def test_a_failed_pool_start_is_raised_by_starting():
    class Broken:
        """An executor whose workers cannot start: every task fails."""

        def submit(self, fn, *args):
            fut: Future = Future()
            fut.set_exception(OSError("cannot start"))
            return fut

    runner = Runner(2, "processes", make_executor=Broken)
    starting = runner.start_in_background()
    deadline = time.monotonic() + 60
    with pytest.raises(OSError, match="cannot start"):
        while starting() and time.monotonic() < deadline:
            time.sleep(0.01)


def test_dask_without_the_extra_names_it(monkeypatch):
    """``--dask`` where Dask's ``distributed`` is not installed: one line naming the extra."""
    import sys

    from colmap_miho.extras import MissingExtraError

    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(MissingExtraError, match=r"pip install 'colmap-miho\[dask\]'"), open_runner(2, LOCAL):
        pass


def lsm_step_loaded() -> bool:
    from colmap_miho.refinement.lsm import kernel as lsm_kernel

    return lsm_kernel.KERNELS.loaded


def test_dask_workers_load_the_runs_kernels_before_their_first_task():
    """Each Dask worker fills its machine's kernel cache once (a worker plugin) and loads the
    run's families before any task: no task pays their compilation or loading."""
    with open_runner(2, LOCAL, families=("lsm",)) as runner:
        assert all(runner.submit(lsm_step_loaded).result() for _ in range(4))
    with open_runner(2, LOCAL) as runner:  # no families: nothing loaded ahead
        assert not runner.submit(lsm_step_loaded).result()
