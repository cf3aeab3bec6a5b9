"""Nothing of ours, and nothing of the libraries we call, is left in ``$TMPDIR`` after a run:
glog's own log files, Dask's scratch space, multiprocessing's ``pymp-*`` folders."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from helpers import REPO


def _cli(args: list[str], tmpdir: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "TMPDIR": str(tmpdir), "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get(
        "PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "colmap_miho", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_verbose_leaves_no_glog_files_in_tmpdir(db_copy, scene, tmp_path):
    """``-v`` shows COLMAP's log on the terminal; glog's default also wrote
    ``.<host>.<user>.log.INFO.<time>.<pid>`` (and WARNING, ERROR) into TMPDIR, never removed."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    done = _cli(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--output",
                 str(tmp_path / "out.db"), "--workers", "1", "--no-refine", "--set", "match_check.mode=remove",
                 "-v"], tmp)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "global_pipeline" in done.stderr or "I20" in done.stderr  # COLMAP's log did reach the terminal
    assert "Could not read image" not in done.stderr  # the global mapper is not given the images, on purpose
    assert sorted(p.name for p in tmp.iterdir()) == []


def _refine_args(db: Path, images: Path, out: Path, *extra: str) -> list[str]:
    return ["refine", "--database", str(db), "--images", str(images), "--output", str(out), "--no-refine", "-q",
            *extra]


def test_after_kill_9_the_next_run_removes_what_was_left(db_copy, scene, tmp_path):
    """A run with worker processes killed (-9) in the global mapper leaves its folders in
    TMPDIR (multiprocessing's, the estimate's): none is a ``pymp-*`` folder that nothing can
    tell the owner of, and the next run, even one with no workers, removes them."""
    import shutil
    import tempfile

    from helpers import HELPERS

    # a short TMPDIR: the forkserver's socket path must fit AF_UNIX's 107 bytes in our folder
    tmp = Path(tempfile.mkdtemp(prefix="k9", dir="/tmp"))
    try:
        _kill_9_then_run(db_copy, scene, tmp_path, tmp, HELPERS)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _kill_9_then_run(db_copy, scene, tmp_path: Path, tmp: Path, helpers: Path) -> None:
    import signal
    import time

    marker = tmp_path / "marker"
    env = {**os.environ, "TMPDIR": str(tmp), "MIHO_TEST_POOL": "1"}
    proc = subprocess.Popen([sys.executable, str(helpers / "busy_in_mapper.py"), str(marker),
                             *_refine_args(db_copy, scene.image_dir, tmp_path / "a.db", "--workers", "2", "--set",
                                           "match_check.mode=remove")],
                            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    left = sorted(p.name for p in tmp.iterdir())
    assert marker.exists() and any(n.startswith("miho-mp-") for n in left), left
    assert any(n.startswith("miho-global-") for n in left) and not any(n.startswith("pymp-") for n in left), left
    time.sleep(2)  # the orphaned workers and forkserver notice and end
    done = _cli(["export", "--database", str(db_copy), "--features", str(tmp_path / "f.h5"), "--matches",
                 str(tmp_path / "m.h5"), "-q"], tmp)
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(p.name for p in tmp.iterdir()) == []


def test_dask_leaves_no_scratch_space_in_tmpdir(db_copy, scene, tmp_path):
    """A local Dask cluster's workers write ``dask-scratch-space/`` into TMPDIR and Dask leaves
    it there after every run: it goes into a folder of ours, removed with the run."""
    import pytest

    pytest.importorskip("distributed")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    done = _cli([*_refine_args(db_copy, scene.image_dir, tmp_path / "o.db", "--workers", "2", "--dask")], tmp)
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(p.name for p in tmp.iterdir()) == []


def test_a_tmpdir_too_deep_for_our_folder_leaves_multiprocessing_its_own(tmp_path):
    """The forkserver's socket must fit AF_UNIX's 107 bytes: where ``miho-mp-*`` would not,
    multiprocessing keeps its own (shorter) ``pymp-*`` folder, removed at exit as always."""
    code = ("import multiprocessing.process as p\n"
            "from colmap_miho.pipeline import workers\n"
            "workers.MAX_SOCKET_PATH = 10\n"
            "workers.private_multiprocessing_tempdir()\n"
            "print(p.current_process()._config.get('tempdir'))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "TMPDIR": str(tmp_path)})
    assert done.returncode == 0 and done.stdout.strip() == "None", done.stderr
    assert list(tmp_path.iterdir()) == []
