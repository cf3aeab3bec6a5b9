"""What each signal does to a refine run: Ctrl-C (SIGINT), SIGTERM and SIGHUP (the terminal
closed, ssh dropped) stop it with one line, remove the working files and keep the finished work
for ``--resume``, whether Python serves the signal or a long COLMAP call holds the interpreter."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import HELPERS, REPO

from colmap_miho.cli import TERM_GRACE_S
from colmap_miho.pipeline.store import store_folder

CODES = {"SIGINT": 130, "SIGTERM": 143, "SIGHUP": 129}


def _start_in_mapper(db: Path, images: Path, out: Path, tmp: Path, marker: Path, workers: int = 1,
                     group: bool = False) -> subprocess.Popen:
    env = {**os.environ, "TMPDIR": str(tmp), **({"MIHO_TEST_POOL": "1"} if workers > 1 else {})}
    proc = subprocess.Popen(
        [sys.executable, str(HELPERS / "busy_in_mapper.py"), str(marker), "refine", "--database", str(db),
         "--images", str(images), "--output", str(out), "--workers", str(workers), "-q", "--no-refine", "--set",
         "match_check.mode=remove"],
        cwd=REPO, stderr=subprocess.PIPE, text=True, env=env, start_new_session=group)
    deadline = time.monotonic() + 120
    while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    if not marker.exists():
        proc.kill()
        pytest.fail(f"the mapper never started: {proc.communicate()[1][-2000:]}")
    return proc


@pytest.mark.parametrize(("sig", "workers"), [("SIGINT", 1), ("SIGTERM", 1), ("SIGHUP", 1), ("SIGTERM", 2)])
def test_a_signal_during_a_colmap_call_says_the_work_is_kept(db_copy, scene, tmp_path, sig, workers):
    """The watcher's forced exit (the interpreter is held by the mapper) says the same as the
    line Python prints: the working files removed, the finished work kept, ``--resume``; with
    worker processes no more (multiprocessing's "leaked semaphore objects" warning)."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "out.db"
    proc = _start_in_mapper(db_copy, scene.image_dir, out, tmp, tmp_path / "marker", workers)
    try:
        t0 = time.monotonic()
        proc.send_signal(getattr(signal, sig))
        _, err = proc.communicate(timeout=TERM_GRACE_S + 30)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert proc.returncode == CODES[sig] and took < TERM_GRACE_S + 20, err
    assert len(lines) == 1 and "during a COLMAP call" in lines[0], lines
    assert f"the finished work of this run is kept in {store_folder(out)}" in lines[0], lines
    assert "--resume" in lines[0] and store_folder(out).is_dir(), lines
    assert list(tmp.iterdir()) == [] and not out.exists()


def test_sighup_served_by_python_is_a_sigterm(db_copy, scene, tmp_path):
    """SIGHUP while Python runs: the same clean-up and line as SIGTERM, exit 129."""
    from helpers import start_at_write

    out = tmp_path / "out.db"
    proc = start_at_write("hold_at_write.py", tmp_path / "marker", str(tmp_path / "never"), "refine",
                          "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                          "--workers", "1", "--no-refine", "-q")
    try:
        proc.send_signal(signal.SIGHUP)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert proc.returncode == 129 and len(lines) == 1, err
    assert lines[0].startswith("ERROR: hung up (SIGHUP); working files removed"), lines
    assert not out.exists() and [p.name for p in out.parent.iterdir() if p.name.startswith(".out.db")] in (
        [], [store_folder(out).name]), list(out.parent.iterdir())


def test_closing_the_terminal_hangs_up_the_whole_group_cleanly(db_copy, scene, tmp_path):
    """A closed terminal sends SIGHUP to every process of its group: the workers, the
    forkserver and multiprocessing's resource tracker too. A tracker killed by it was started
    again, and printed a KeyError traceback for every semaphore it never saw."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "out.db"
    proc = _start_in_mapper(db_copy, scene.image_dir, out, tmp, tmp_path / "marker", workers=2, group=True)
    try:
        os.killpg(proc.pid, signal.SIGHUP)
        _, err = proc.communicate(timeout=TERM_GRACE_S + 30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert proc.returncode == 129 and len(lines) == 1, err
    assert lines[0].startswith("ERROR: hung up (SIGHUP)") and "--resume" in lines[0], lines
    assert list(tmp.iterdir()) == [] and not out.exists()


@pytest.mark.parametrize("sig", ["SIGHUP", "SIGINT"])
def test_a_signal_ignored_at_start_stays_ignored(db_copy, scene, tmp_path, sig):
    """``nohup colmap-miho refine ... &`` (SIGHUP ignored) and a script that ignores SIGINT for
    its background jobs: the signal, sent mid-run, does nothing; the run finishes and writes
    its output, as any Unix tool would."""
    from helpers import start_at_write

    out = tmp_path / "out.db"
    resume = tmp_path / "resume"
    proc = start_at_write("hold_at_write.py", tmp_path / "marker", str(resume), "refine",
                          "--database", str(db_copy), "--images", str(scene.image_dir), "--output", str(out),
                          "--workers", "1", "--no-refine", "-q", ignored=(getattr(signal, sig),))
    try:
        proc.send_signal(getattr(signal, sig))
        time.sleep(0.5)
        resume.write_text("go")
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert out.is_file() and not store_folder(out).exists()


def test_a_signal_a_callback_swallowed_is_said(monkeypatch, capfd, tmp_path):
    """An interrupt raised inside a compiled kernel's callback can be swallowed there (printed
    as "Exception ignored"): the run then finishes; it must not end 0 without a word."""
    from colmap_miho.cli import main
    from colmap_miho.commands import report

    def swallowing(args) -> int:
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            pass  # what a callback that cannot raise does
        return 0

    monkeypatch.setattr(report, "run", swallowing)
    assert main(["report", "--model", str(tmp_path), "-q"]) == 0
    err = capfd.readouterr().err
    assert "arrived inside a compiled kernel, which lost it" in err and "output is complete" in err, err
    # the forced-exit watcher ends with the command: it once slept on and ended the caller 60 s later
    import threading

    deadline = time.monotonic() + 3
    while any(t.name == "sigterm-watch" for t in threading.enumerate()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(t.name == "sigterm-watch" for t in threading.enumerate())


@pytest.mark.parametrize("in_place", [False, True])
def test_a_signal_after_the_commit_says_the_output_was_written(db_copy, scene, tmp_path, capfd, monkeypatch,
                                                                in_place):
    """Ctrl-C while the run store is removed after the commit: the output is complete (in place:
    the input was replaced, its backup kept), so the line must not say "nothing was written to the
    input" (a rerun in place would refine it twice), nor leave the store for a --resume that fails
    on the existing output."""
    from colmap_miho.cli import main
    from colmap_miho.pipeline.store import RunStore

    remove = RunStore.remove

    def interrupted(self):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C, as the commit is done
        return remove(self)

    monkeypatch.setattr(RunStore, "remove", interrupted)
    before = db_copy.read_bytes()
    out = db_copy if in_place else tmp_path / "out.db"
    capfd.readouterr()
    code = main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--no-refine",
                 "--workers", "1", "-q", *(["--in-place"] if in_place else ["--output", str(out)])])
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert code == 130 and len(lines) == 1, lines
    assert "nothing was written" not in lines[0] and f"{out} was written" in lines[0], lines
    assert out.is_file() and not os.path.lexists(store_folder(out))
    assert (db_copy.read_bytes() != before) == in_place
