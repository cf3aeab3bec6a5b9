"""Refine stage of ``refine_database``: the track-consistent NCC walk, in this process or in
``spawn``-ed worker processes (see :mod:`.workers`) with one BLAS/torch thread each.

Results do not depend on the worker count: refinement chunks are whole tracks, which never
share a keypoint.
"""

from __future__ import annotations

import contextlib
import logging
import os
from concurrent.futures import FIRST_COMPLETED, wait

import numpy as np

from ..adapters.images import ImageLoader
from .workers import process_pool as _process_pool

log = logging.getLogger(__name__)

#: Refinement runs in worker processes only with at least this many refinable matches each.
MIN_MATCHES_PER_REFINE_WORKER = 2000


def _import_refinement():
    """The track plan and walk, imported only when a run refines (they import torch)."""
    from ..refinement import track_plan, tracks

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
        while queue is not None and bar is not None and not queue.empty():
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
