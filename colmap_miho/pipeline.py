"""``refine_database``: filter and refine the matches of a COLMAP database, safely.

Data flow (one stage after the other)::

    safe working copy -> read pairs -> filter each pair (MOP / MOP+MiHo, parallel)
      -> track-consistent NCC refinement -> write back (keypoints, matches,
      two_view_geometries) -> optional COLMAP re-verification -> atomic replace

The input database is never opened for writing; see :mod:`colmap_miho.io.safety`.

Parallelism: pairs are filtered, and whole tracks refined, in ``spawn``-ed worker processes
with one BLAS/torch thread each; in-process refinement also uses one torch thread (measured
on the 2-core machine: one torch thread 4x faster than two for the NCC walk; threads over
track chunks were slower than one thread: the walk holds the GIL).
Scripts that call :func:`refine_database` with ``workers > 1`` need the usual
``if __name__ == "__main__":`` guard.
All coordinates handled here are colmap-miho's (integer = pixel centre); the conversion to
COLMAP's happens inside :mod:`colmap_miho.io.database`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .enums import Device, MatchSource
from .errors import DatabaseError, RunFailed, UserError
from .io.database import ColmapDatabase, validate_database
from .io.images import ImageLoader
from .io.safety import WorkingCopy, check_database_path
from .recipe import Recipe, load_recipe

log = logging.getLogger(__name__)

#: Test hook: when set to a file path, the write stage creates that file and then sleeps,
#: so that a test can kill the process in the middle of writing.
PAUSE_AT_WRITE_ENV = "COLMAP_MIHO_DEBUG_PAUSE_AT_WRITE"
#: Below this many pairs to filter per worker, filtering runs in this process (starting a
#: worker process costs seconds: it imports torch).
MIN_PAIRS_PER_WORKER = 4
#: Refinement runs in worker processes only with at least this many refinable matches each.
MIN_MATCHES_PER_REFINE_WORKER = 2000


@dataclass
class RefineSummary:
    """What ``refine_database`` did. Counters are over image pairs / matches / keypoints.

    Attributes:
        output: path of the written database.
        backup: timestamped copy of the input (``in_place`` only), else None.
        pairs_filtered: pairs with at least ``pipeline.min_matches`` matches, filtered.
        pairs_passed: pairs with fewer matches, left unchanged.
        pairs_failed: filtered pairs for which the filter found no plane; left unchanged.
        matches_in / matches_kept / matches_removed: over the filtered (successful) pairs.
        keypoints_moved: keypoints whose position changed (each moves at most once).
        median_displacement_px / max_displacement_px: over the moved keypoints, pixels.
        images_missing: names of images that could not be read (not refined).
        seconds: wall time per stage ("copy", "read", "filter", "refine", "write", "verify",
            "total").
    """

    output: Path
    database: Path
    backup: Path | None = None
    recipe: str = ""
    source: str = ""
    refined: bool = True
    verified: bool = False
    workers: int = 1
    device: str = "cpu"
    num_images: int = 0
    num_pairs: int = 0
    pairs_filtered: int = 0
    pairs_passed: int = 0
    pairs_failed: int = 0
    matches_in: int = 0
    matches_kept: int = 0
    matches_removed: int = 0
    keypoints_total: int = 0
    keypoints_moved: int = 0
    median_displacement_px: float = 0.0
    max_displacement_px: float = 0.0
    images_missing: list[str] = field(default_factory=list)
    refine_stats: dict = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Plain JSON-ready data (paths as strings, seconds rounded to ms)."""
        out = dataclasses.asdict(self)
        for key in ("output", "database", "backup"):
            out[key] = None if out[key] is None else str(out[key])
        out["seconds"] = {k: round(v, 3) for k, v in self.seconds.items()}
        return out

    def format(self) -> str:
        """A one-screen human summary."""
        kept_pct = 100.0 * self.matches_kept / self.matches_in if self.matches_in else 0.0
        lines = [
            f"colmap-miho refine: {self.database} -> {self.output}",
            f"  recipe {self.recipe}, source {self.source}, refine {'on' if self.refined else 'off'}, "
            f"verify {'on' if self.verified else 'off'}, {self.workers} worker(s), {self.device}",
            f"  images {self.num_images}, pairs {self.num_pairs}: {self.pairs_filtered} filtered, "
            f"{self.pairs_passed} too small (unchanged), {self.pairs_failed} no plane found (unchanged)",
            f"  matches {self.matches_in} -> kept {self.matches_kept} ({kept_pct:.1f}%), "
            f"removed {self.matches_removed}",
            f"  keypoints moved {self.keypoints_moved} of {self.keypoints_total}, median displacement "
            f"{self.median_displacement_px:.2f} px, max {self.max_displacement_px:.2f} px",
        ]
        if self.images_missing:
            lines.append(f"  images not refined (missing/unreadable): {', '.join(self.images_missing)}")
        if self.backup:
            lines.append(f"  backup of the input: {self.backup}")
        lines.append("  seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in self.seconds.items()))
        return "\n".join(lines)


def _resolve_recipe(recipe: Recipe | str | os.PathLike | None) -> Recipe:
    if isinstance(recipe, Recipe):
        return recipe
    return load_recipe(None if recipe is None else str(recipe))


def _resolve_device(device: Device | str) -> str:
    device = Device.parse(device, "device")
    if device == Device.CPU:
        return "cpu"
    import torch

    if device == Device.CUDA:
        if not torch.cuda.is_available():
            raise UserError("--device cuda was asked for but torch sees no CUDA device")
        return "cuda"
    return "cuda" if torch.cuda.is_available() else "cpu"


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
    from .filtering.api import filter_matches

    result = filter_matches(pts1, pts2, method=filter_config.method, config=filter_config, seed=seed)
    return i, j, result


def _filter_pairs(db: ColmapDatabase, pairs, keypoints, source, filter_config, *, seed: int,
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
            import multiprocessing

            ctx = multiprocessing.get_context("spawn")
            with _single_thread_children(), \
                    ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker) as ex:
                pending = set()
                it = iter(pairs)
                try:
                    for p in it:
                        pending.add(ex.submit(_filter_one, *job(p)))
                        if len(pending) >= 2 * workers:
                            done, pending = wait(pending, return_when=FIRST_COMPLETED)
                            for fut in done:
                                i, j, res = fut.result()
                                results[(i, j)] = (matches_of.pop((i, j)), res)
                                if bar:
                                    bar.update()
                    for fut in pending:
                        i, j, res = fut.result()
                        results[(i, j)] = (matches_of.pop((i, j)), res)
                        if bar:
                            bar.update()
                except BaseException:
                    ex.shutdown(wait=False, cancel_futures=True)
                    raise
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
        from .refinement.tracks import refine_tracks
    except ImportError as exc:  # the refinement module ships separately
        raise RunFailed(f"NCC refinement is not available ({exc}); use --no-refine") from None
    return refine_tracks


def _refine_chunk(loader_state, keypoints, pair_matches, pair_results, ncc_config, track_config,
                  affines, threads):
    """Worker: refine_tracks on a set of whole tracks; returns (keypoints, stats)."""
    import torch

    torch.set_num_threads(max(1, int(threads)))
    refine_tracks = _import_refine_tracks()
    loader = ImageLoader(**loader_state)
    tr = refine_tracks(loader, keypoints, pair_matches, pair_results, ncc_config=ncc_config,
                       track_config=track_config, affines=affines, progress=False)
    return tr.keypoints, tr.stats


def _split_tracks(keypoints, pairs, workers: int):
    """Split the refinable matches into ``workers`` chunks of whole tracks (connected
    components over (image, keypoint) nodes), balanced by match count.

    Returns a list of (pair_matches, pair_results) per chunk; tracks never straddle chunks, so
    each keypoint can move in one chunk only and the chunks' results merge without conflict.
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
    return [c for c in chunks if c[0]]


def _refine(loader: ImageLoader, keypoints, pairs, affines, ncc_config, track_config, *,
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
    chunks = _split_tracks(keypoints, pairs, use)
    state = dict(image_dir=loader.image_dir, names=loader.names, max_cached=loader.max_cached)
    threads = max(1, (os.cpu_count() or 1) // len(chunks))
    import multiprocessing

    new = {i: keypoints[i].copy() for i in keypoints}
    stats: dict = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(chunks), desc="NCC tracks (chunks)", unit="chunk")
    try:
        with ProcessPoolExecutor(max_workers=len(chunks), mp_context=multiprocessing.get_context("spawn")) as ex:
            futs = [ex.submit(_refine_chunk, state, keypoints, pm, pr, ncc_config, track_config, affines, threads)
                    for pm, pr in chunks]
            try:
                for fut in futs:
                    kp, st = fut.result()
                    for i, arr in kp.items():
                        arr = np.asarray(arr, np.float64)
                        changed = np.any(arr != keypoints[i], axis=1)
                        new[i][changed] = arr[changed]
                    for key, v in _numeric(st).items():
                        stats[key] = stats.get(key, 0) + v
                    if bar:
                        bar.update()
            except BaseException:
                ex.shutdown(wait=False, cancel_futures=True)
                raise
    finally:
        if bar:
            bar.close()
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


def _pause_for_tests(stage: str) -> None:
    marker = os.environ.get(PAUSE_AT_WRITE_ENV)
    if marker:
        Path(marker).write_text(stage)
        time.sleep(60)


def refine_database(
    database: str | os.PathLike,
    image_dir: str | os.PathLike,
    output: str | os.PathLike | None = None,
    *,
    recipe: Recipe | str | os.PathLike | None = None,
    in_place: bool = False,
    overwrite: bool = False,
    workers: int | None = None,
    device: Device | str = "auto",
    seed: int = 0,
    strict: bool = False,
    progress: bool = False,
    json_path: str | os.PathLike | None = None,
) -> RefineSummary:
    """Filter (MOP / MOP+MiHo) and refine (track-consistent NCC) a COLMAP database.

    Args:
        database: the input COLMAP database; never opened for writing (unless ``in_place``,
            and even then only replaced atomically at the end, after a backup).
        image_dir: folder the database's image names are relative to.
        output: the database to write; default ``<stem>.miho.db`` beside the input.
        recipe: a :class:`~colmap_miho.recipe.Recipe`, a shipped recipe name or a TOML path
            (default ``mop_miho_ncc``); its ``pipeline`` table chooses the match source,
            ``min_matches``, refinement and re-verification.
        in_place: replace ``database`` itself, after copying it to a timestamped backup.
        overwrite: allow replacing an existing ``output``.
        workers: processes that filter pairs and refine tracks (default: all cores; 1 = all
            in this process). Small jobs stay in this process (a worker costs an import of
            torch); results do not depend on the worker count.
        device: "cpu", "cuda" or "auto" for the torch work.
        seed: base seed; each pair's filter seed is derived from it and the pair's image ids.
        strict: a missing or unreadable image is an error instead of a warning.
        progress: show tqdm progress bars.
        json_path: also write :meth:`RefineSummary.to_dict` as JSON to this file.

    Returns:
        A :class:`RefineSummary`.

    Raises:
        DatabaseError: missing or non-COLMAP database, database in use.
        UserError: bad image folder, existing output without ``overwrite``, strict and an
            image missing, no pairs to process.
        ValueError: a bad recipe or option value (the message names it).
    """
    t_start = time.perf_counter()
    seconds: dict[str, float] = {}
    database = check_database_path(database)
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise UserError(f"image folder not found: {image_dir}")
    rec = _resolve_recipe(recipe)
    pcfg = rec.pipeline
    dev = _resolve_device(device)
    fcfg = dataclasses.replace(rec.filter, device=dev) if rec.filter.device == "auto" else rec.filter
    ncfg = dataclasses.replace(rec.ncc, device=dev) if rec.ncc.device == "auto" else rec.ncc
    n_workers = max(1, int(workers) if workers else (os.cpu_count() or 1))
    if dev == "cuda":
        n_workers = 1  # one process owns the GPU

    summary = RefineSummary(output=Path(output) if output else database, database=database,
                            recipe=rec.name, source=str(pcfg.source), refined=pcfg.refine,
                            verified=pcfg.verify, device=dev)
    wc = WorkingCopy(database, Path(output) if output else None, in_place=in_place, overwrite=overwrite)
    t_copy = time.perf_counter()
    seconds["setup"] = t_copy - t_start
    with wc:
        seconds["copy"] = time.perf_counter() - t_copy
        validate_database(wc.path)
        t = time.perf_counter()
        with ColmapDatabase(wc.path) as db:
            images = db.images()
            if not images:
                raise DatabaseError(f"database has no images: {database}")
            names = {im.image_id: im.name for im in images}
            keypoints = {im.image_id: db.keypoints(im.image_id) for im in images}
            pairs = db.pairs(pcfg.source)
            if not pairs:
                raise DatabaseError(
                    f"database has no image pairs with {pcfg.source} matches: {database}"
                    + (" (try --source raw)" if pcfg.source == MatchSource.VERIFIED else "")
                )
            to_filter = [p for p in pairs if p.num_matches >= pcfg.min_matches]
            summary.num_images = len(images)
            summary.num_pairs = len(pairs)
            summary.pairs_passed = len(pairs) - len(to_filter)
            summary.keypoints_total = int(sum(len(k) for k in keypoints.values()))
            loader = ImageLoader(image_dir, names, max_cached=rec.tracks.max_images_in_memory,
                                 expected_sizes={im.image_id: (im.width, im.height) for im in images})
            if pcfg.refine:
                missing = loader.check_all()
                summary.images_missing = [names[i] for i in missing]
                if missing and strict:
                    raise UserError(f"image missing or unreadable (--strict): {loader.path(missing[0])}"
                                    + (f" and {len(missing) - 1} more" if len(missing) > 1 else ""))
            seconds["read"] = time.perf_counter() - t

            t = time.perf_counter()
            workers_used = n_workers if len(to_filter) >= MIN_PAIRS_PER_WORKER * n_workers else 1
            summary.workers = workers_used
            filtered = _filter_pairs(db, to_filter, keypoints, pcfg.source, fcfg, seed=seed,
                                     workers=workers_used, progress=progress)
            ok = {k: v for k, v in filtered.items() if bool(v[1].success)}
            summary.pairs_filtered = len(filtered)
            summary.pairs_failed = len(filtered) - len(ok)
            summary.matches_in = int(sum(len(m) for m, _ in ok.values()))
            summary.matches_kept = int(sum(int(np.count_nonzero(r.inliers)) for _, r in ok.values()))
            summary.matches_removed = summary.matches_in - summary.matches_kept
            seconds["filter"] = time.perf_counter() - t

            t = time.perf_counter()
            new_keypoints = keypoints
            if pcfg.refine and ok:
                usable = {k: v for k, v in ok.items()
                          if k[0] not in loader.missing and k[1] not in loader.missing}
                affines = {i: db.keypoint_affines(i) for i in keypoints}
                affines = None if any(a is None for a in affines.values()) else affines
                new_keypoints, stats, refine_workers = _refine(
                    loader, keypoints, usable, affines, ncfg, rec.tracks,
                    workers=1 if dev == "cuda" else n_workers, progress=progress)
                summary.refine_stats = dict(stats, workers=refine_workers)
            seconds["refine"] = time.perf_counter() - t

            t = time.perf_counter()
            displacements = []
            with db.transaction():
                for image_id, old in keypoints.items():
                    new = new_keypoints[image_id]
                    moved = np.any(new != old, axis=1) if len(old) else np.zeros(0, bool)
                    if moved.any():
                        displacements.append(np.linalg.norm(new[moved] - old[moved], axis=1))
                        db.write_keypoints(image_id, new, moved)
                for n_written, ((i, j), (m, r)) in enumerate(sorted(ok.items())):
                    if n_written == len(ok) // 2:
                        _pause_for_tests("write")
                    kept = m[np.asarray(r.inliers, bool)]
                    db.write_pair(i, j, kept, new_keypoints[i][kept[:, 0]], new_keypoints[j][kept[:, 1]],
                                  keep_model=pcfg.source == MatchSource.VERIFIED)
                if pcfg.verify:
                    db.delete_two_view_geometries(sorted(ok))
            d = np.concatenate(displacements) if displacements else np.zeros(0)
            summary.keypoints_moved = int(d.size)
            summary.median_displacement_px = float(np.median(d)) if d.size else 0.0
            summary.max_displacement_px = float(d.max()) if d.size else 0.0
            seconds["write"] = time.perf_counter() - t

        if pcfg.verify:
            t = time.perf_counter()
            _reverify(wc.path)
            seconds["verify"] = time.perf_counter() - t
        summary.output = wc.commit()
        summary.backup = wc.backup
    seconds["total"] = time.perf_counter() - t_start
    summary.seconds = seconds
    if json_path:
        Path(json_path).write_text(json.dumps(summary.to_dict(), indent=2) + "\n", encoding="utf-8")
    log.info("wrote %s", summary.output)
    return summary


def _reverify(path: Path) -> None:
    """COLMAP's own epipolar verification of the pairs that have matches and no geometry."""
    import pycolmap

    pycolmap.geometric_verification(str(path))
