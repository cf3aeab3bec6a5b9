"""The worker pool: forked by the forkserver (which imported torch once), spawn when the
forkserver cannot start; a dead worker, and a script without a ``__main__`` guard, are one
clear error."""

from __future__ import annotations

import math
import multiprocessing
import os
import subprocess
import sys

import pytest
from helpers.db_contents import database_rows

from colmap_miho.errors import RunFailed
from colmap_miho.pipeline import workers
from colmap_miho.pipeline.refine_job import refine_database
from miho_bench.synthetic import make_synthetic_scene

pytestmark = pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(),
                                reason="no forkserver on this platform")


@pytest.fixture(scope="module")
def every_family_cached():
    """Every kernel family in the cache (compiled now if missing) and a forkserver started
    after that (a server started earlier loaded only what the cache held then)."""
    from multiprocessing import forkserver

    from colmap_miho.kernel_cache import ensure_compiled

    assert not ensure_compiled().failed
    forkserver._forkserver._stop()  # type: ignore[attr-defined]


def test_workers_come_from_the_forkserver():
    with workers.process_pool(2) as ex:
        assert ex._mp_context.get_start_method() == "forkserver"
        ppids = {ex.submit(os.getppid).result(timeout=120) for _ in range(4)}
    assert os.getpid() not in ppids  # their parent is the server, not this process


def _kernels_loaded() -> bool:
    from colmap_miho.filtering.compiled import miho, ransac, sampling, scoring

    return all(m.KERNELS.loaded for m in (sampling, scoring, ransac, miho))


def test_workers_start_with_the_compiled_filter_kernels_loaded(every_family_cached):
    """The forkserver loads the filter kernels once (from the cache); a worker forked from it
    has them before it filters anything."""
    assert "colmap_miho.kernel_preload" in workers.PRELOAD
    with workers.process_pool(1) as ex:
        assert ex.submit(_kernels_loaded).result(timeout=300)


def _ncc_kernels_loaded() -> bool:
    from colmap_miho.refinement.ncc import kernel as ncc_kernel

    return ncc_kernel.KERNELS.loaded


def test_workers_start_with_the_compiled_ncc_kernels_loaded(every_family_cached):
    """The same for the NCC search and sub-pixel kernels of the track walk."""
    with workers.process_pool(1) as ex:
        assert ex.submit(_ncc_kernels_loaded).result(timeout=300)


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


def test_a_dead_worker_is_one_clear_error():
    with pytest.raises(RunFailed, match="worker process ended abruptly.*__main__"):
        with workers.process_pool(1) as ex:
            ex.submit(os._exit, 3).result(timeout=120)


def test_a_run_started_while_a_worker_imports_the_main_script_is_refused(monkeypatch, tmp_path):
    monkeypatch.setattr(multiprocessing.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(RunFailed, match="__main__"):
        refine_database(tmp_path / "missing.db", tmp_path)  # refused before looking at anything


UNGUARDED = """
from colmap_miho.pipeline import filter as filter_stage
from colmap_miho.pipeline import track_groups
from colmap_miho.pipeline.refine_job import refine_database

filter_stage.MIN_PAIRS_PER_WORKER = 1  # both stages use the workers even for this scene
filter_stage.MIN_MATCHES_PER_FILTER_WORKER = 0
track_groups.MIN_MATCHES_PER_REFINE_WORKER = 10
track_groups.MIN_MATCHES_TO_START_WORKERS = 0
refine_database({db!r}, {images!r}, {out!r}, workers=2, device="cpu", dask={dask!r})
"""


@pytest.mark.parametrize("dask, error", [
    (None, "a worker process ended abruptly"),
    ("local", "the local Dask cluster did not start"),
])
def test_a_script_without_a_main_guard_gets_the_fix_in_its_error(tmp_path, dask, error):
    """Python's workers (and Dask's) import the script that started them; an unguarded call
    used to end in a bare BrokenProcessPool or "Nanny failed to start" (and started a second
    run in each worker)."""
    scene = make_synthetic_scene(tmp_path / "scene", num_images=4, num_points=60, seed=3)
    before = database_rows(scene.database)
    script = tmp_path / "unguarded.py"
    script.write_text(UNGUARDED.format(db=str(scene.database), images=str(scene.image_dir),
                                       out=str(tmp_path / "out.db"), dask=dask))
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path)
    assert run.returncode != 0
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith(f"colmap_miho.errors.RunFailed: {error}")
    assert "if __name__ == \"__main__\":" in last
    assert not (tmp_path / "out.db").exists()
    assert database_rows(scene.database) == before  # the input is untouched


def _affine_kernels_loaded() -> bool:
    from colmap_miho.refinement.rectify import kernel as affine_kernel

    return affine_kernel.KERNELS.loaded


def test_workers_start_with_the_compiled_local_affine_fits_loaded(every_family_cached):
    """The same for the local affine fits of the track walk."""
    with workers.process_pool(1) as ex:
        assert ex.submit(_affine_kernels_loaded).result(timeout=300)


def _lsm_kernel_loaded() -> bool:
    from colmap_miho.refinement.lsm import kernel as lsm_kernel

    return lsm_kernel.KERNELS.loaded


def test_workers_start_with_the_compiled_lsm_step_loaded(every_family_cached):
    """The same for the LSM step (recipes with ``lsm.enabled``)."""
    with workers.process_pool(1) as ex:
        assert ex.submit(_lsm_kernel_loaded).result(timeout=300)
