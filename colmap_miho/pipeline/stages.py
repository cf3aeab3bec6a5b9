"""The two heavy stages of ``refine_database``: filtering pairs and the track-consistent NCC
walk, each in this process or in ``spawn``-ed worker processes with one BLAS/torch thread each.

Measured on the 2-core machine: one torch thread is 4x faster than two for the NCC walk, and
threads over track chunks were slower than one thread (the walk holds the GIL), hence processes.
Results do not depend on the worker count: each pair's seed is derived from its image ids and
refinement chunks are whole tracks, which never share a keypoint.
"""

from __future__ import annotations

import contextlib
import logging
import os
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

import numpy as np

from ..errors import RunFailed
from ..adapters.database import ColmapDatabase
from ..adapters.images import ImageLoader

log = logging.getLogger(__name__)

#: Refinement runs in worker processes only with at least this many refinable matches each.
MIN_MATCHES_PER_REFINE_WORKER = 2000


def pair_seed(seed: int, image_id1: int, image_id2: int) -> int:
    """Seed of one pair, independent of worker count and order."""
    return int(np.random.SeedSequence([int(seed), int(image_id1), int(image_id2)]).generate_state(1)[0])


_SINGLE_THREAD_ENV = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def _init_worker() -> None:
    """One thread per worker process (the parallelism is across pairs)."""
    import sys

    if "torch" in sys.modules:  # the filter is numpy; only pay for torch if it is loaded
        sys.modules["torch"].set_num_threads(1)


@contextlib.contextmanager
def _single_thread_children():
    """Spawned workers inherit the environment: make their BLAS/OpenMP single-threaded."""
    saved = {k: os.environ.get(k) for k in _SINGLE_THREAD_ENV}
    os.environ.update(_SINGLE_THREAD_ENV)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _filter_one(i: int, j: int, pts1: np.ndarray, pts2: np.ndarray, filter_config, seed: int):
    """Run the filter on one pair (in a worker or in-process); returns (i, j, result)."""
    from ..filtering.api import filter_matches

    result = filter_matches(pts1, pts2, method=filter_config.method, config=filter_config, seed=seed)
    return i, j, result


def run_filter_stage(db: ColmapDatabase, pairs, keypoints, source, filter_config, *, seed: int,
                  workers: int, progress: bool):
    """Filter every pair, streaming matches from the database into a bounded worker queue.

    Returns dict (i, j) -> (matches uint32 (M, 2), FilterResult).
    """
    results: dict[tuple[int, int], tuple[np.ndarray, object]] = {}
    matches_of: dict[tuple[int, int], np.ndarray] = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(pairs), desc="filter pairs", unit="pair")

    def job(p):
        m = db.matches(p.image_id1, p.image_id2, source)
        matches_of[(p.image_id1, p.image_id2)] = m
        return (p.image_id1, p.image_id2, keypoints[p.image_id1][m[:, 0]],
                keypoints[p.image_id2][m[:, 1]], filter_config, pair_seed(seed, p.image_id1, p.image_id2))

    try:
        if workers <= 1:
            for p in pairs:
                i, j, res = _filter_one(*job(p))
                results[(i, j)] = (matches_of.pop((i, j)), res)
                if bar:
                    bar.update()
        else:
            with _single_thread_children(), _process_pool(workers, initializer=_init_worker) as ex:
                def collect(fut) -> None:
                    i, j, res = fut.result()
                    results[(i, j)] = (matches_of.pop((i, j)), res)
                    if bar:
                        bar.update()

                pending = set()
                for p in pairs:
                    pending.add(ex.submit(_filter_one, *job(p)))
                    if len(pending) >= 2 * workers:  # bounded: stream pairs, do not queue all
                        done, pending = wait(pending, return_when=FIRST_COMPLETED)
                        for fut in done:
                            collect(fut)
                for fut in pending:
                    collect(fut)
    finally:
        if bar:
            bar.close()
    return results


def _import_refinement():
    try:
        from ..refinement import track_plan, tracks
    except ImportError as exc:  # the refinement module ships separately
        raise RunFailed(f"NCC refinement is not available ({exc}); use --no-refine") from None
    return track_plan.build_track_plan, tracks.walk_tracks, tracks.local_affine_of


def _refine_chunk(loader_state, plan, ncc_config, track_config, affines, threads,
                  progress_queue=None):
    """Worker: walk the whole tracks of ``plan``; returns (keypoints, stats). Reports the
    keypoints it has handled on ``progress_queue`` (a manager queue) when given."""
    import torch

    torch.set_num_threads(max(1, int(threads)))
    _, walk_tracks, _ = _import_refinement()
    report = progress_queue.put if progress_queue is not None else None
    tr = walk_tracks(ImageLoader(**loader_state), plan, ncc_config=ncc_config,
                     track_config=track_config, affines=affines, progress=False,
                     on_progress=report)
    return tr.keypoints, tr.stats


def _merge_walk_stats(plan_stats: dict, parts: list[dict]) -> dict:
    """The plan's stats, the parts' counters summed (``levels``: the deepest part)."""
    from ..refinement.tracks import WALK_COUNTERS

    stats = dict(plan_stats)
    for key in WALK_COUNTERS + ("missing_images", "images_loaded", "seconds"):
        vals = [st[key] for st in parts if key in st]
        if vals:
            stats[key] = max(vals) if key in ("levels", "missing_images") else sum(vals)
    return _numeric(stats)


def run_refine_stage(loader: ImageLoader, keypoints, pairs, affines, ncc_config, track_config, *,
                     unrefined=None, workers: int, progress: bool):
    """Track-consistent NCC refinement, in this process or in ``workers`` processes (each
    walks whole tracks of one :class:`~colmap_miho.refinement.track_plan.TrackPlan`).

    Args:
        pairs: (i, j) -> (matches (M, 2), FilterResult with rows 1:1) of the filtered pairs
            whose images are present.
        unrefined: (i, j) -> (M, 2) the other matches that reach the output database (pairs
            not filtered, failed, or with a missing image): they join tracks, never refine.
    Returns:
        (new keypoints dict, stats, processes used).
    """
    build_track_plan, walk_tracks, local_affine_of = _import_refinement()
    plan = build_track_plan(keypoints, {k: m for k, (m, _) in pairs.items()},
                            {k: r for k, (_, r) in pairs.items()}, unrefined_matches=unrefined,
                            duplicate_px=track_config.duplicate_px,
                            local_affine=local_affine_of(ncc_config))
    n_edges = int(plan.refinable().sum())
    if not n_edges:
        return keypoints, _numeric(plan.stats), 1
    use = min(workers, max(1, n_edges // MIN_MATCHES_PER_REFINE_WORKER))
    if use <= 1:
        with _torch_threads(1 if ncc_config.device != "cuda" else None):
            tr = walk_tracks(loader, plan, ncc_config=ncc_config, track_config=track_config,
                             affines=affines, progress=progress)
        new = {i: np.asarray(tr.keypoints.get(i, keypoints[i]), np.float64) for i in keypoints}
        return new, _numeric(tr.stats), 1
    parts = plan.partition(use)
    state = dict(image_dir=loader.image_dir, names=loader.names, max_cached=loader.max_cached)
    threads = max(1, (os.cpu_count() or 1) // len(parts))
    import multiprocessing

    new = {i: keypoints[i].copy() for i in keypoints}
    part_stats: list[dict] = []
    bar = queue = manager = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=plan.to_refine, desc=f"NCC tracks ({len(parts)} workers)", unit="kp")
        manager = multiprocessing.get_context("spawn").Manager()
        queue = manager.Queue()

    def drain() -> None:
        while queue is not None and not queue.empty():
            bar.update(queue.get())

    try:
        with _process_pool(len(parts)) as ex:
            futs = [ex.submit(_refine_chunk, state, part, ncc_config, track_config, affines,
                              threads, queue)
                    for part in parts]
            pending = set(futs)
            while pending:
                done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                drain()
                for fut in done:
                    fut.result()  # a failed worker stops the run now, not at the end
            for fut in futs:
                kp, st = fut.result()
                for i, arr in kp.items():
                    arr = np.asarray(arr, np.float64)
                    changed = np.any(arr != keypoints[i], axis=1)
                    new[i][changed] = arr[changed]
                part_stats.append(st)
            drain()
    finally:
        if bar:
            bar.close()
        if manager is not None:
            manager.shutdown()
    return new, _merge_walk_stats(plan.stats, part_stats), len(parts)


@contextlib.contextmanager
def _process_pool(workers: int, **kwargs):
    """A spawn process pool whose queued work is cancelled, not waited for, when the block
    raises (a failed worker, Ctrl-C)."""
    import multiprocessing

    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             **kwargs) as ex:
        try:
            yield ex
        except BaseException:
            ex.shutdown(wait=False, cancel_futures=True)
            raise


@contextlib.contextmanager
def _torch_threads(n: int | None):
    """Run a block with ``n`` torch intra-op threads, then restore the caller's setting.

    Measured on the 2-core machine (fountain, 55 pairs): the NCC walk took 54 s with one
    torch thread and 4x longer with two (many small ops; threading overhead dominates).
    """
    if n is None:
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _numeric(stats: dict) -> dict:
    return {k: v for k, v in stats.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
