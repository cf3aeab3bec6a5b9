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
from dataclasses import dataclass

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


@dataclass(frozen=True)
class _PairRows:
    """The refinable rows of one pair for one refinement chunk (rows 1:1 with its matches)."""

    inliers: np.ndarray
    labels: np.ndarray
    patch_homographies: np.ndarray


def _import_refine_tracks():
    try:
        from ..refinement.tracks import refine_tracks
    except ImportError as exc:  # the refinement module ships separately
        raise RunFailed(f"NCC refinement is not available ({exc}); use --no-refine") from None
    return refine_tracks


def _refine_chunk(loader_state, keypoints, pair_matches, pair_results, ncc_config, track_config,
                  affines, threads, progress_queue=None):
    """Worker: refine_tracks on a set of whole tracks; returns (keypoints, stats). Reports the
    keypoints it has handled on ``progress_queue`` (a manager queue) when given."""
    import torch

    torch.set_num_threads(max(1, int(threads)))
    refine_tracks = _import_refine_tracks()
    loader = ImageLoader(**loader_state)
    report = progress_queue.put if progress_queue is not None else None
    tr = refine_tracks(loader, keypoints, pair_matches, pair_results, ncc_config=ncc_config,
                       track_config=track_config, affines=affines, progress=False,
                       on_progress=report)
    return tr.keypoints, tr.stats


def _split_tracks(keypoints, pairs, workers: int):
    """Split the refinable matches into ``workers`` chunks of whole tracks (connected
    components over (image, keypoint) nodes), balanced by match count.

    Returns (a list of (pair_matches, pair_results) per chunk, the number of keypoints the
    walk will refine: all keypoints in tracks but one anchor per track). Tracks never
    straddle chunks, so each keypoint can move in one chunk only and the chunks' results merge
    without conflict.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    offset, total = {}, 0
    for i in sorted(keypoints):
        offset[i] = total
        total += len(keypoints[i])
    keys = sorted(pairs)
    rows, ea, eb = {}, [], []
    for k in keys:
        m, r = pairs[k]
        labels = np.asarray(r.labels, np.int64).reshape(-1)
        rr = np.flatnonzero(labels >= 0)
        rows[k] = rr
        ea.append(offset[k[0]] + m[rr, 0].astype(np.int64))
        eb.append(offset[k[1]] + m[rr, 1].astype(np.int64))
    ea, eb = np.concatenate(ea), np.concatenate(eb)
    _, comp = connected_components(coo_matrix((np.ones(ea.size), (ea, eb)), shape=(total, total)),
                                   directed=False)
    nodes = np.unique(np.concatenate([ea, eb]))
    to_refine = int(nodes.size - np.unique(comp[nodes]).size)
    edge_comp = comp[ea]
    sizes = np.bincount(edge_comp, minlength=comp.max() + 1)
    order = np.argsort(-sizes, kind="stable")
    load = np.zeros(workers)
    chunk_of_comp = np.zeros(sizes.size, np.int64)
    for c in order[sizes[order] > 0]:  # greedy: biggest track to the lightest chunk
        b = int(np.argmin(load))
        chunk_of_comp[c] = b
        load[b] += sizes[c]
    edge_chunk = chunk_of_comp[edge_comp]
    chunks = [({}, {}) for _ in range(workers)]
    start = 0
    for k in keys:
        m, r = pairs[k]
        rr = rows[k]
        ch = edge_chunk[start:start + rr.size]
        start += rr.size
        labels = np.asarray(r.labels, np.int64).reshape(-1)
        homs = np.asarray(r.patch_homographies, np.float64)
        for b in np.unique(ch):
            sel = rr[ch == b]
            chunks[b][0][k] = m[sel]
            chunks[b][1][k] = _PairRows(np.ones(sel.size, bool), labels[sel], homs)
    return [c for c in chunks if c[0]], to_refine


def run_refine_stage(loader: ImageLoader, keypoints, pairs, affines, ncc_config, track_config, *,
            workers: int, progress: bool):
    """Track-consistent NCC refinement, in this process or in ``workers`` processes (each
    refines whole tracks). Returns (new keypoints dict, summed stats, processes used)."""
    n_edges = sum(int(np.count_nonzero(np.asarray(r.labels) >= 0)) for _, r in pairs.values())
    if not n_edges:
        return keypoints, {}, 1
    use = min(workers, max(1, n_edges // MIN_MATCHES_PER_REFINE_WORKER))
    if use <= 1:
        refine_tracks = _import_refine_tracks()
        with _torch_threads(1 if ncc_config.device != "cuda" else None):
            tr = refine_tracks(loader, keypoints, {k: m for k, (m, _) in pairs.items()},
                               {k: r for k, (_, r) in pairs.items()}, ncc_config=ncc_config,
                               track_config=track_config, affines=affines, progress=progress)
        new = {i: np.asarray(tr.keypoints.get(i, keypoints[i]), np.float64) for i in keypoints}
        return new, _numeric(tr.stats), 1
    _import_refine_tracks()  # fail early, in this process, if it is missing
    chunks, to_refine = _split_tracks(keypoints, pairs, use)
    state = dict(image_dir=loader.image_dir, names=loader.names, max_cached=loader.max_cached)
    threads = max(1, (os.cpu_count() or 1) // len(chunks))
    import multiprocessing

    new = {i: keypoints[i].copy() for i in keypoints}
    stats: dict = {}
    bar = queue = manager = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=to_refine, desc=f"NCC tracks ({len(chunks)} workers)", unit="kp")
        manager = multiprocessing.get_context("spawn").Manager()
        queue = manager.Queue()

    def drain() -> None:
        while queue is not None and not queue.empty():
            bar.update(queue.get())

    try:
        with _process_pool(len(chunks)) as ex:
            futs = [ex.submit(_refine_chunk, state, keypoints, pm, pr, ncc_config, track_config,
                              affines, threads, queue)
                    for pm, pr in chunks]
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
                for key, v in _numeric(st).items():
                    stats[key] = stats.get(key, 0) + v
            drain()
    finally:
        if bar:
            bar.close()
        if manager is not None:
            manager.shutdown()
    return new, stats, len(chunks)


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
