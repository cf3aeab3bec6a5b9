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
    assert sorted(p.name for p in tmp.iterdir()) == []
