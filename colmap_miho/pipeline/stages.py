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
from dataclasses import dataclass

import numpy as np

from ..adapters.images import ImageLoader
from .workers import process_pool as _process_pool

log = logging.getLogger(__name__)

#: Refinement runs in worker processes only with at least this many refinable matches each.
MIN_MATCHES_PER_REFINE_WORKER = 2000


@dataclass(frozen=True)
class _PairRows:
    """The refinable rows of one pair for one refinement chunk (rows 1:1 with its matches)."""

    inliers: np.ndarray
    labels: np.ndarray
    patch_homographies: np.ndarray


def _import_refine_tracks():
    """``refine_tracks``, imported only when a run refines."""
    from ..refinement.tracks import refine_tracks

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
    rows, ea_parts, eb_parts = {}, [], []
    for k in keys:
        m, r = pairs[k]
        labels = np.asarray(r.labels, np.int64).reshape(-1)
        rr = np.flatnonzero(labels >= 0)
        rows[k] = rr
        ea_parts.append(offset[k[0]] + m[rr, 0].astype(np.int64))
        eb_parts.append(offset[k[1]] + m[rr, 1].astype(np.int64))
    ea, eb = np.concatenate(ea_parts), np.concatenate(eb_parts)
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
    chunks: list[tuple[dict, dict]] = [({}, {}) for _ in range(workers)]
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
        while bar is not None and queue is not None and not queue.empty():
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
