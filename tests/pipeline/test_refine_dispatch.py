"""The refine stage's hand-out of track groups to the runner's slots (``_dispatch``), with a
stand-in walk on a thread pool: every group walked once, each run's groups in order, a run's
next group handed out before the last one's results are applied, its arguments made ahead, and
a slot whose run is done taking the last groups of another run."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import pytest

from colmap_miho.pipeline import track_groups
from colmap_miho.pipeline.executor import Runner


class _Loader:
    names = {1: "a.png", 2: "b.png"}
    expected_sizes = {1: (4, 4), 2: (4, 4)}
    max_cached_bytes = None

    def state(self) -> dict:
        return {"image_dir": "."}


class _Attach:
    def __init__(self, log: list) -> None:
        self.log = log

    def inputs(self, g: int):
        self.log.append(("inputs", g))
        return SimpleNamespace(index=g)


@pytest.mark.parametrize("slots", [1, 2, 3])
def test_dispatch_hands_out_each_group_once_in_run_order(monkeypatch, slots):
    log: list = []
    lock = threading.Lock()

    def fake_walk(state, group, ncc, tracks, aff):
        with lock:
            log.append(("walk", group.index))
        return {}, {"refined": group.index}

    monkeypatch.setattr(track_groups, "_walk_group_task", fake_walk)
    groups = [SimpleNamespace(to_refine=n, image_ids=[1, 2]) for n in (5, 9, 2, 7, 4, 8, 3)]
    todo = [0, 1, 2, 4, 5, 6]  # group 3 resumed
    runner = Runner(slots, "processes", make_executor=lambda: ThreadPoolExecutor(slots))
    submitted: list = []
    real_submit = runner.submit

    def submit(fn, *args):
        with lock:
            submitted.append(args[1].index)
            log.append(("submit", args[1].index))
        return real_submit(fn, *args)

    runner.submit = submit  # type: ignore[method-assign]
    finished: list = []

    def finish(g, moved, st):
        assert st == {"refined": g}
        with lock:
            finished.append(g)
            log.append(("finish", g))

    track_groups._dispatch(runner, _Loader(), groups, todo, slots, _Attach(log),
                           (None, None, None, None), finish, None)
    runner.executor().shutdown()
    assert sorted(finished) == sorted(submitted) == todo
    runs = track_groups._runs([groups[g] for g in todo], slots)
    for run in runs:
        mine = [todo[k] for k in run]
        order = [g for g in submitted if g in mine]
        # the run's own slot hands out its groups from the front, in order; idle slots take
        # groups from its end: the order merges the first k groups with the rest reversed
        own = next(mine[:k] for k in range(len(mine), -1, -1)
                   if [g for g in order if g in mine[:k]] == mine[:k]
                   and [g for g in order if g in mine[k:]] == mine[k:][::-1])
        for a, b in zip(own[:-1], own[1:], strict=True):
            # the next group is handed out before the last one's results are applied
            assert log.index(("submit", b)) < log.index(("finish", a))
            # and its arguments were made before the last one returned
            assert log.index(("inputs", b)) < log.index(("finish", a))
    assert sum(1 for e in log if e[0] == "inputs") == len(todo)  # each group's arguments once


def test_an_idle_slot_takes_the_last_groups_of_a_busy_run(monkeypatch):
    """Runs [0, 1, 2] and [3]: group 0's walk lasts until group 2 has been walked, which only
    the slot whose run (group 3) is done can do, taking it from the busy run's end."""
    walked_2 = threading.Event()
    order: list = []
    lock = threading.Lock()

    def fake_walk(state, group, ncc, tracks, aff):
        if group.index == 0:
            assert walked_2.wait(timeout=20.0), "no idle slot took group 2"
        with lock:
            order.append(group.index)
        if group.index == 2:
            walked_2.set()
        return {}, {"refined": group.index}

    monkeypatch.setattr(track_groups, "_walk_group_task", fake_walk)
    groups = [SimpleNamespace(to_refine=n, image_ids=[1, 2]) for n in (3, 3, 3, 10)]
    todo = [0, 1, 2, 3]
    assert track_groups._runs(groups, 2) == [[0, 1, 2], [3]]
    runner = Runner(2, "processes", make_executor=lambda: ThreadPoolExecutor(2))
    finished: list = []
    track_groups._dispatch(runner, _Loader(), groups, todo, 2, _Attach([]), (None, None, None, None),
                           lambda g, moved, st: finished.append(g), None)
    runner.executor().shutdown()
    assert sorted(finished) == todo
    assert order.index(2) < order.index(0)
