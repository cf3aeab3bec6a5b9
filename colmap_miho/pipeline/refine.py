"""``refine_database``: filter and refine the matches of a COLMAP database, safely.

Data flow (one stage after the other, each ``run_<stage>`` returning its outputs and a small
stats dataclass that :class:`RefineSummary` is assembled from)::

    safe working copy -> read (:mod:`.read`) -> filter the pairs chunk by chunk
      (:mod:`.filter_stage`, MOP / MOP+MiHo) into the run store (:mod:`.store`)
      -> track-consistent NCC refinement (:mod:`.stages`) -> write back chunk by chunk
      (:mod:`.write`: keypoints, matches, two_view_geometries)
      -> optional COLMAP re-verification (:mod:`.verify`) -> atomic replace

The input database is never opened for writing; see :mod:`colmap_miho.adapters.safety`.

Memory: ``pipeline.memory_budget_mb`` (``refine --memory-budget``) sizes the filter's chunks
and the refine stage's image cache (see :class:`~.config.PipelineConfig`).

Resuming: finished filter chunks and refine groups are kept in the run store beside the
output until the commit; a killed or failed run is continued with ``resume=True``
(``refine --resume``), and ``restart=True`` discards them. A run that finds finished work
and was given neither refuses to start.

Parallelism: one :class:`~.executor.Runner` per run (:func:`~.executor.open_runner`) runs the
filter's chunks and the refinement's track groups in this process, in worker processes with one
thread each (forked from a forkserver that imported torch once), or on a Dask cluster
(``dask``); only this process writes SQLite. Scripts that call :func:`refine_database` with
``workers > 1`` need the usual ``if __name__ == "__main__":`` guard.
All coordinates handled here are colmap-miho's
(integer = pixel centre); the conversion to COLMAP's happens inside
:mod:`colmap_miho.adapters.database`.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import os
import sqlite3
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..adapters.database import ColmapDatabase, validate_database
from ..adapters.paths import check_distinct
from ..adapters.safety import WorkingCopy, check_database_path
from ..enums import Device
from ..errors import DatabaseError, RunFailed, UserError
from . import stages
from .executor import Runner, open_runner
from .filter_stage import FilteredPairs, FilterOptions, FilterStats, run_filter
from .pair_check import run_pair_check
from .read import ReadConfig, ReadOutput, ReadStats, read_affines, run_read
from .stages import DECODED_BY_IMAGE, run_refine_stage
from .store import RunStore, run_fingerprint, store_folder
from .verify import run_verify
from .workers import check_not_bootstrapping, start_forkserver
from .write import WriteStats, run_write

if TYPE_CHECKING:  # recipe.py imports this package's config: import it lazily
    from ..recipe import Recipe

log = logging.getLogger(__name__)


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
        runner: where the parallel work ran: "inline", "processes" or "dask".
        memory_budget_mb: ``pipeline.memory_budget_mb`` of the run.
        filter_chunks / filter_chunks_resumed: chunks of pairs filtered in all / taken from
            an interrupted run's store; pairs_resumed: the pairs of those chunks.
        refine_groups / refine_groups_resumed: track groups refined in all / taken from the
            store (0 when the refine stage does not report groups).
        resumed: the run continued an interrupted one.
        image_decodes: image files decoded in the whole run, over all processes: the read
            stage's check (once per image; kept in the cache when it fits) and the track walk's
            (an image again in each worker whose groups need it and no longer cache it).
        image_decodes_max: the most times one image was decoded in the run (same count).
        pair_check: what the pair check removed or flagged, and why
            (:meth:`~.pair_check.PairCheckStats.to_dict`; empty when it is off).
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
    runner: str = "inline"
    memory_budget_mb: int = 0
    filter_chunks: int = 0
    filter_chunks_resumed: int = 0
    pairs_resumed: int = 0
    refine_groups: int = 0
    refine_groups_resumed: int = 0
    resumed: bool = False
    image_decodes: int = 0
    image_decodes_max: int = 0
    refine_stats: dict = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    pair_check: dict = field(default_factory=dict)

    @classmethod
    def from_stages(cls, *, output: Path, database: Path, backup: Path | None, recipe: Recipe,
                    device: str, runner: str, resumed: bool, read: ReadStats, filtered: FilterStats,
                    refine_stats: dict, write: WriteStats, seconds: dict[str, float]) -> RefineSummary:
        """Assemble the summary from the stages' stats."""
        pcfg = recipe.pipeline
        refine_stats = dict(refine_stats)
        per_image = Counter(read.decoded_by_image)
        per_image.update({int(k): int(v) for k, v in refine_stats.pop(DECODED_BY_IMAGE, {}).items()})
        return cls(
            output=output, database=database, backup=backup, recipe=recipe.name,
            source=str(pcfg.source), refined=pcfg.refine, verified=pcfg.verify,
            workers=filtered.workers, device=device, num_images=read.num_images,
            num_pairs=read.num_pairs, pairs_filtered=filtered.pairs_filtered,
            pairs_passed=read.pairs_passed, pairs_failed=filtered.pairs_failed,
            matches_in=filtered.matches_in, matches_kept=filtered.matches_kept,
            matches_removed=filtered.matches_removed, keypoints_total=read.keypoints_total,
            keypoints_moved=write.keypoints_moved,
            median_displacement_px=write.median_displacement_px,
            max_displacement_px=write.max_displacement_px,
            images_missing=list(read.images_missing), runner=runner, memory_budget_mb=pcfg.memory_budget_mb,
            filter_chunks=filtered.chunks, filter_chunks_resumed=filtered.chunks_resumed,
            pairs_resumed=filtered.pairs_resumed, refine_groups=int(refine_stats.get("groups", 0)),
            refine_groups_resumed=int(refine_stats.get("groups_resumed", 0)), resumed=resumed,
            image_decodes=read.image_decodes + int(refine_stats.get("image_decodes", 0)),
            image_decodes_max=max(per_image.values(), default=0),
            refine_stats=refine_stats, seconds=seconds)

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
            f"verify {'on' if self.verified else 'off'}, {self.workers} worker(s) ({self.runner}), {self.device}",
            f"  images {self.num_images}, pairs {self.num_pairs}: {self.pairs_filtered} filtered, "
            f"{self.pairs_passed} too small (unchanged), {self.pairs_failed} no plane found (unchanged)",
            f"  matches {self.matches_in} -> kept {self.matches_kept} ({kept_pct:.1f}%), "
            f"removed {self.matches_removed}",
            f"  keypoints moved {self.keypoints_moved} of {self.keypoints_total}, median displacement "
            f"{self.median_displacement_px:.2f} px, max {self.max_displacement_px:.2f} px",
        ]
        if self.resumed:
            lines.append(f"  resumed: {self.filter_chunks_resumed} of {self.filter_chunks} filter chunks "
                         f"({self.pairs_resumed} pairs) and {self.refine_groups_resumed} of "
                         f"{self.refine_groups} refine groups were finished before")
        if self.pair_check:
            pc = self.pair_check
            done = f"{pc['pairs_removed']} removed" if pc["mode"] == "remove" else f"{pc['pairs_flagged']} flagged"
            lines.append(f"  pair check: {pc['pairs_checked']} pairs, {pc['triangles']} triangles "
                         f"({pc['triangles_broken']} broken), {done}"
                         + "".join(f"\n    {' - '.join(w['images'])}: {w['reason']}" for w in pc["wrong_pairs"][:10])
                         + (f"\n    ... and {len(pc['wrong_pairs']) - 10} more (see the JSON report)"
                            if len(pc["wrong_pairs"]) > 10 else ""))
        if self.images_missing:
            lines.append(f"  images not refined (missing/unreadable): {', '.join(self.images_missing)}")
        if self.backup:
            lines.append(f"  backup of the input: {self.backup}")
        lines.append("  seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in self.seconds.items()))
        return "\n".join(lines)


def _resolve_recipe(recipe: Recipe | str | os.PathLike | None) -> Recipe:
    from ..recipe import Recipe, load_recipe

    if isinstance(recipe, Recipe):
        return recipe
    return load_recipe(None if recipe is None else str(recipe))


def _resolve_device(device: Device | str) -> str:
    """"cpu" or "cuda", by the refinement's resolver (torch is imported only if needed)."""
    device = Device.parse(device, "device")
    if device == Device.CPU:
        return "cpu"
    from ..refinement.config import NCCConfig
    from ..refinement.ncc import resolve_device

    try:
        return resolve_device(NCCConfig(device=str(device))).type
    except ValueError:
        raise UserError("--device cuda was asked for but torch sees no CUDA device") from None


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
    resume: bool = False,
    restart: bool = False,
    dask: str | None = None,
) -> RefineSummary:
    """Filter (MOP / MOP+MiHo) and refine (track-consistent NCC) a COLMAP database.

    Args:
        database: the input COLMAP database; never opened for writing (unless ``in_place``,
            and even then only replaced atomically at the end, after a backup).
        image_dir: folder the database's image names are relative to.
        output: the database to write; default ``<stem>.miho.db`` beside the input.
        recipe: a :class:`~colmap_miho.recipe.Recipe`, a shipped recipe name or a TOML path
            (default ``mop_miho_ncc``); its ``pipeline`` table chooses the match source,
            ``min_matches``, refinement, re-verification and the memory budget.
        in_place: replace ``database`` itself, after copying it to a timestamped backup.
        overwrite: allow replacing an existing ``output``.
        workers: processes that filter pairs and refine tracks (default: all cores; 1 = all
            in this process), or the workers of a local Dask cluster. Small jobs stay in
            this process (below ~10k matches per worker, workers do not pay off); results do
            not depend on the worker count.
        device: "cpu", "cuda" or "auto" for the torch work.
        seed: base seed; each pair's filter seed is derived from it and the pair's image ids.
        strict: a missing or unreadable image is an error instead of a warning.
        progress: show tqdm progress bars.
        json_path: also write :meth:`RefineSummary.to_dict` as JSON to this file.
        resume: continue an interrupted run from its run store (``.<output name>.miho-run``
            beside the output); the inputs and options must be those of that run.
        restart: discard an interrupted run's store and start again.
        dask: None (no Dask), ``"local"`` (a local Dask cluster of ``workers`` processes) or
            a scheduler address ``tcp://host:8786``; the workers must see ``image_dir`` at
            the same path.

    Returns:
        A :class:`RefineSummary`.

    Raises:
        DatabaseError: missing or non-COLMAP database, database in use.
        UserError: bad image folder, existing output without ``overwrite``, strict and an
            image missing, no pairs to process; an interrupted run's store found without
            ``resume`` or ``restart``, or ``resume`` with other inputs or options.
        ValueError: a bad recipe or option value (the message names it).
        RunFailed: a worker process died (see :data:`~.workers.WORKER_DIED`), or this is
            a worker importing a script that calls this without a ``__main__`` guard.
    """
    check_not_bootstrapping()
    laps = _Laps()
    database = check_database_path(database)
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise UserError(f"image folder not found: {image_dir}")
    rec = _resolve_recipe(recipe)
    asked = max(1, int(workers) if workers else (os.cpu_count() or 1))
    if asked > 1 and dask is None and str(device) != "cuda":
        start_forkserver()  # the workers' imports run beside this process's from here on
    dev = _resolve_device(device)
    n_workers = 1 if dev == "cuda" else asked
    wc = WorkingCopy(database, Path(output) if output else None, in_place=in_place, overwrite=overwrite)
    check_distinct({"--database": database, "--images": image_dir},
                   {"--output": None if in_place else wc.output, "--json": json_path})
    if json_path:
        _check_writable_file(Path(json_path), "--json")
    store = RunStore.open(store_folder(wc.output), run_fingerprint(database, image_dir, rec, seed, dev),
                          resume=resume, restart=restart)
    resumed = store.has_work()
    laps.lap("setup")
    try:
        with open_runner(n_workers, dask) as runner:
            summary = _run_stages(database, image_dir, wc, store, runner, rec, dev, seed=seed, strict=strict,
                                  progress=progress, json_path=json_path, resumed=resumed, laps=laps)
    except UserError as exc:  # one line: the error, then how to resume
        if not _keep_store(store):
            raise
        raise type(exc)(f"{exc}; {_resume_hint(store)}") from exc
    except BaseException as exc:  # the CLI prints the note on the error's one line
        if _keep_store(store):
            _add_note(exc, _resume_hint(store))
        raise
    store.remove()
    log.info("wrote %s", summary.output)
    return summary


def _keep_store(store: RunStore) -> bool:
    """After a failure: keep the store when it holds finished work (else remove it); True
    when kept."""
    if store.has_work():
        store.close()
        return True
    store.remove()
    return False


def _add_note(exc: BaseException, note: str) -> None:
    """``exc.add_note(note)`` (Python >= 3.11), or the same ``__notes__`` list on 3.10."""
    add = getattr(exc, "add_note", None)
    if add is not None:
        add(note)
    else:  # pragma: no cover - Python 3.10
        exc.__notes__ = [*getattr(exc, "__notes__", []), note]  # type: ignore[attr-defined]


def _resume_hint(store: RunStore) -> str:
    return (f"the finished work of this run is kept in {store.folder}: run the same command with "
            "--resume to continue it (or --restart to start again)")


def _run_stages(database: Path, image_dir: Path, wc: WorkingCopy, store: RunStore, runner: Runner,
                rec: Recipe, dev: str, *, seed: int, strict: bool, progress: bool,
                json_path: str | os.PathLike | None, resumed: bool, laps: _Laps) -> RefineSummary:
    """The stages on the working copy, then the commit; returns the summary."""
    pcfg = rec.pipeline
    try:
        with wc:
            laps.lap("copy")
            work_db = wc.path
            assert work_db is not None  # set on entering the block
            try:
                validate_database(work_db)
            except DatabaseError as exc:  # name the user's file, not the hidden working copy
                raise DatabaseError(str(exc).replace(str(work_db), str(database))) from None
            with ColmapDatabase(work_db) as db:
                read, read_stats = run_read(db, ReadConfig(
                    pipeline=pcfg, image_dir=image_dir, image_budget_bytes=pcfg.image_budget_bytes(runner.slots),
                    strict=strict, database_name=database))
                laps.lap("read")
                filter_stats = run_filter(db, read.to_filter, read.keypoints, rec.filter, FilterOptions(
                    source=pcfg.source, seed=seed, memory_budget_bytes=pcfg.memory_budget_bytes, device=dev,
                    progress=progress, database_name=str(database)), runner=runner, store=store)
                laps.lap("filter")
                removed, pair_check = run_pair_check(db, read, store, rec.pair_check, pcfg.source)
                if rec.pair_check.enabled:
                    laps.lap("pair_check")
                new_keypoints, refine_stats = _refine(db, read, store, rec, dev, runner, progress, removed)
                laps.lap("refine")
                write_stats = run_write(db, read.keypoints, new_keypoints, store.iter_filter_chunks(), pcfg,
                                        removed=removed)
                laps.lap("write")
            if pcfg.verify:
                run_verify(work_db)
                laps.lap("verify")
            summary = RefineSummary.from_stages(
                output=database if wc.in_place else wc.output,  # in place: the user's path (a symlink stays one)
                database=database, backup=wc.backup, recipe=rec, device=dev, runner=runner.kind,
                resumed=resumed, read=read_stats, filtered=filter_stats, refine_stats=refine_stats,
                write=write_stats, seconds=laps.total())
            summary.pair_check = pair_check
            if json_path:  # written beside its target now, renamed onto it with the commit
                wc.stage_side_file(json_path, json.dumps(summary.to_dict(), indent=2) + "\n")
            wc.commit()
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        raise RunFailed(f"disk full while writing in {wc.output.parent}; {database} is unchanged and the "
                        "working files were removed: free some space and retry") from None
    except sqlite3.Error as exc:
        raise RunFailed(f"SQLite error while writing the copy of {database} ({exc}); {database} is "
                        "unchanged and the working files were removed") from None
    return summary


def _check_writable_file(path: Path, label: str) -> None:
    """Refuse, before any work, an output file whose folder is missing or read-only.

    Raises:
        UserError: the message names the option and the path.
    """
    if path.is_dir():
        raise UserError(f"{label} {path} is a folder; give a file name")
    if not path.parent.is_dir():
        raise UserError(f"{label} folder does not exist: {path.parent}")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise UserError(f"{label} {path}: cannot write in {path.parent} (read-only folder)")


def _refine(db: ColmapDatabase, read: ReadOutput, store: RunStore, rec: Recipe, device: str,
            runner: Runner, progress: bool, removed: set[tuple[int, int]]) -> tuple[dict[int, np.ndarray], dict]:
    """Refine stage on the stored pairs whose two images are readable, on ``runner``, skipping
    the track groups ``store`` holds and storing each finished one; returns the new keypoints
    and the summed refinement counters with the processes used (``{}`` when refinement is off
    or nothing was filtered). The ``removed`` pairs (pair check) join no track."""
    if not rec.pipeline.refine or not store.filter_counts().pairs_ok:
        return read.keypoints, {}
    ok = {k: v for k, v in store.load_filtered().items() if k not in removed}
    missing = read.loader.missing
    usable = {k: v for k, v in ok.items() if k[0] not in missing and k[1] not in missing}
    ncfg = dataclasses.replace(rec.ncc, device=device) if rec.ncc.device == "auto" else rec.ncc
    budget = rec.pipeline.image_budget_bytes(runner.slots)
    # the groups are numbered for one image budget: stored groups of another are walked again
    done = store.refine_groups({"image_budget_bytes": budget, "group_max_matches": stages.group_max_matches()})
    new_keypoints, stats, used = run_refine_stage(
        read.loader, read.keypoints, usable, read_affines(db, read.keypoints), ncfg, rec.tracks,
        unrefined=_unrefined_matches(db, ok, usable, rec.pipeline.source, removed), runner=runner,
        progress=progress, image_budget_bytes=budget, done=done, on_group=store.save_group)
    # the images skipped before the walk count as missing too: the same number as images_missing
    return new_keypoints, dict(stats, workers=used,
                               missing_images=max(int(stats.get("missing_images", 0)), len(missing)))


def _unrefined_matches(db: ColmapDatabase, ok: FilteredPairs, usable: FilteredPairs,
                       source, removed: set[tuple[int, int]]) -> dict[tuple[int, int], np.ndarray]:
    """Every match that reaches the output database but is not refined: the pairs too small to
    filter and the failed ones (written back unchanged), and the kept matches of pairs with a
    missing image. The walk joins them into tracks (they never refine), so a keypoint that moves
    stays consistent with every partner COLMAP will see. The ``removed`` pairs are left out."""
    out = {}
    for p in db.pairs(source):
        key = (p.image_id1, p.image_id2)
        if key in usable or key in removed:
            continue
        if key in ok:
            m, r = ok[key]
            out[key] = m[np.asarray(r.inliers, bool)]
        else:
            out[key] = db.matches(p.image_id1, p.image_id2, source)
    return out


class _Laps:
    """Wall time per stage: each :meth:`lap` records the time since the previous one."""

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.seconds: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = now - self.last
        self.last = now

    def total(self) -> dict[str, float]:
        self.seconds["total"] = time.perf_counter() - self.start
        return self.seconds
