"""The ``refine`` command's job, :func:`refine_database`: filter, check and refine the matches of a
COLMAP database, safely.

Data flow (one stage after the other, each ``run_<stage>`` returning its outputs and a small
stats dataclass that :class:`RefineSummary` is assembled from)::

    safe working copy -> read (:mod:`.read`) -> filter the pairs chunk by chunk
      (:mod:`.filter`, MOP / MOP+MiHo) into the run store (:mod:`.store`)
      -> match check against a global estimate of the cameras (:mod:`.match_check_stage`, its
      :class:`~.verdicts.Verdicts`)
      -> track-consistent NCC refinement (:mod:`.refine_keypoints`) -> write back chunk by chunk
      (:mod:`.write`: keypoints, matches, two_view_geometries)
      -> optional COLMAP re-verification (:mod:`.reverify`) -> atomic replace

The input database is never opened for writing; see :mod:`colmap_miho.adapters.safety`.

Memory: ``pipeline.memory_budget_mb`` (``refine --memory-budget``) sizes the filter's chunks
and the keypoint refinement's image cache (see :class:`~colmap_miho.pipeline_config.PipelineConfig`).

Resuming: finished filter chunks and refine groups are kept in the run store beside the
output until the commit; a killed or failed run is continued with ``resume=True``
(``refine --resume``), and ``restart=True`` discards them. A run that finds finished work
and was given neither refuses to start.

Parallelism: one :class:`~.executor.Runner` per run (:func:`~.executor.open_runner`) runs the
filter's chunks and the refinement's track groups in this process, in worker processes with one
thread each (forked from a forkserver that imported torch once), or on a Dask cluster
(``dask``); only this process writes SQLite. Scripts that call :func:`refine_database` with
``workers > 1`` need the usual ``if __name__ == "__main__":`` guard.

All coordinates handled here are colmap-miho's (integer = pixel centre); the conversion to
COLMAP's happens inside :mod:`colmap_miho.adapters.database`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ..adapters.database import ColmapDatabase, validate_database
from ..adapters.paths import check_distinct
from ..adapters.safety import check_database_path, exit_note
from ..adapters.working_copy import SideFileLost, WorkingCopy
from ..arguments import check_paths, check_seed, check_workers
from ..enums import Device
from ..errors import InvalidInput, RunFailed, UserError
from ..kernel_cache import ensure_compiled, families_for
from ..recipe import Recipe, load_recipe
from .executor import LOCAL, Runner, open_runner
from .filter import FilterOptions, run_filter
from .match_check_stage import run_match_check
from .read import ReadConfig, run_read
from .refine_keypoints import run_refine_keypoints
from .reverify import run_reverify
from .store import RunStore, StoreDamaged, run_fingerprint, store_folder
from .summary import RefineSummary
from .workers import check_not_bootstrapping, start_forkserver
from .write import run_write

log = logging.getLogger(__name__)


def _resolve_recipe(recipe: Recipe | str | os.PathLike | None) -> Recipe:
    if isinstance(recipe, Recipe):
        return recipe
    return load_recipe(None if recipe is None else str(recipe))


def _resolve_device(device: Device | str) -> str:
    """"cpu" or "cuda", by the one resolver (torch is imported only if needed)."""
    device = Device.parse(device, "device")
    if device == Device.CPU:
        return "cpu"
    from ..devices import resolve_device

    try:
        return resolve_device(device).type
    except ValueError:
        raise UserError("--device cuda was asked for but torch sees no CUDA device") from None


def _check_recipe_device(rec: Recipe) -> None:
    """Refuse ``ncc.device = "cuda"`` where torch sees no CUDA device, before any work (UserError)."""
    if not rec.pipeline.refine_keypoints or Device.parse(rec.ncc.device, "device") != Device.CUDA:
        return
    from ..devices import resolve_device

    try:
        resolve_device(Device.CUDA)
    except ValueError:
        raise UserError("ncc.device=cuda was asked for but torch sees no CUDA device; use ncc.device=auto "
                        "or cpu") from None


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
    """Filter (MOP+MiHo), check and refine (NCC, then least-squares matching) a COLMAP database.

    The keyword arguments are the ``refine`` command's options, one each. Missing compiled kernels
    are compiled first. The input ``database`` is never written (``in_place``: replaced atomically
    after a backup); ``output`` defaults to ``<stem>.miho.db`` beside it. ``recipe``: a
    :class:`~colmap_miho.recipe.Recipe`, shipped name or TOML path. Results do not depend on
    ``workers``; ``seed`` is the run's root seed. ``dask``: ``"local"`` or a scheduler address.

    Returns a :class:`RefineSummary`. Raises :class:`DatabaseError` (missing, non-COLMAP or busy
    database), :class:`UserError` (bad folders, existing output, an interrupted run's store without
    ``resume``/``restart``), ``ValueError`` (a bad option; the message names it) and
    :class:`RunFailed` (a worker died)."""
    check_not_bootstrapping()
    check_paths(database=database, image_dir=image_dir, output=output, json_path=json_path,
                optional=("output", "json_path"))
    check_workers(workers)
    check_seed(seed)
    if dask is not None and not isinstance(dask, str):
        raise InvalidInput(f"dask must be None, 'local' or a scheduler address, got {dask!r}")
    laps = _Laps()
    database = check_database_path(database)
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise UserError(f"image folder not found: {image_dir}")
    rec = _resolve_recipe(recipe)
    _check_recipe_device(rec)  # before any file is made: a run store of a run that cannot run
    asked = max(1, int(workers) if workers else (os.cpu_count() or 1))
    families = families_for(rec)
    if dask is None or dask == LOCAL:  # a remote cluster's workers fill their own machines' caches
        ensure_compiled(families)  # before the forkserver, which loads them from the cache
    if asked > 1 and dask is None and str(device) != "cuda":
        start_forkserver()  # the workers' imports run beside this process's from here on
    dev = _resolve_device(device)
    n_workers = 1 if dev == "cuda" else asked
    wc = WorkingCopy(database, Path(output) if output else None, in_place=in_place, overwrite=overwrite)
    check_distinct({"--database": database, "--images": image_dir},
                   {"--output": None if in_place else wc.output, "--json": json_path})
    if json_path:
        _check_writable_file(Path(json_path), "--json")
        _refuse_inside_run_folder(Path(json_path), store_folder(wc.output))
    store = RunStore.open(store_folder(wc.output), run_fingerprint(database, image_dir, rec, seed, dev),
                          resume=resume, restart=restart)
    resumed = store.has_work()
    laps.lap("setup")
    try:
        with exit_note(lambda: _resume_hint(store) if store.has_work() else ""), \
                open_runner(n_workers, dask, families=families) as runner:
            inputs = _RunInputs(database=database, image_dir=image_dir, recipe=rec, device=dev, seed=seed,
                                strict=strict, progress=progress, json_path=json_path)
            summary = _run_stages(inputs, wc, store, runner, resumed=resumed, laps=laps)
    except StoreDamaged:  # --resume cannot help: the message says --restart
        store.close()
        raise
    except SideFileLost:  # the output is committed: its work is done, --resume would fail on it
        store.remove()
        raise
    except UserError as exc:  # one line: the error, then how to resume
        if not _keep_store(store):
            raise
        raise type(exc)(f"{exc}; {_resume_hint(store)}") from exc
    except BaseException as exc:  # the CLI prints the note on the error's one line
        if _keep_store(store):
            _add_note(exc, _resume_hint(store))
        raise
    try:  # the output is committed: a signal from here on finds the run done
        with _signals_held():
            store.remove()
        log.info("wrote %s", summary.output)
    except BaseException as exc:
        note_output_written(exc, summary)
        raise
    return summary


def note_output_written(exc: BaseException, summary: RefineSummary) -> None:
    """Mark ``exc``, raised after the commit: the output is complete (``exc.output_written``)."""
    in_place = f" (refined in place; its backup: {summary.backup})" if summary.backup else ""
    _add_note(exc, f"{summary.output} was written{in_place} before that and is complete: nothing is left to resume")
    exc.output_written = True  # type: ignore[attr-defined]


@contextlib.contextmanager
def _signals_held():
    """Hold Ctrl-C, SIGTERM and SIGHUP for the block, so the run store is removed whole."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    handlers = {}
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is not None and callable(handler := signal.getsignal(sig)):  # SIG_IGN, SIG_DFL as they are
            handlers[sig] = handler
            signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        if held:
            handlers[held[0]](held[0], None)  # served now (raises, as it would have)


def _keep_store(store: RunStore) -> bool:
    """After a failure keep the store if it holds finished work (else remove it); True when kept."""
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


@dataclass(frozen=True, kw_only=True)
class _RunInputs:
    """What one run's stages read: database, images, resolved recipe and device, run options."""

    database: Path
    image_dir: Path
    recipe: Recipe
    device: str
    seed: int
    strict: bool
    progress: bool
    json_path: str | os.PathLike | None


def _run_stages(inputs: _RunInputs, wc: WorkingCopy, store: RunStore, runner: Runner, *, resumed: bool,
                laps: _Laps) -> RefineSummary:
    """The stages on the working copy, then the commit; returns the summary."""
    database, image_dir, rec, dev = inputs.database, inputs.image_dir, inputs.recipe, inputs.device
    seed, strict, progress, json_path = inputs.seed, inputs.strict, inputs.progress, inputs.json_path
    pcfg = rec.pipeline
    try:
        with wc:
            laps.lap("copy")
            work_db = wc.path
            assert work_db is not None  # set on entering the block
            validate_database(work_db, name=database)  # the messages name the user's file
            with ColmapDatabase(work_db) as db:
                read, read_stats = run_read(db, ReadConfig(
                    pipeline=pcfg, image_dir=image_dir, image_budget_bytes=pcfg.image_budget_bytes(runner.slots),
                    strict=strict, database_name=database))
                laps.lap("read")
                filter_stats = run_filter(db, read.to_filter, read.keypoints, rec.filter, FilterOptions(
                    source=pcfg.source, seed=seed, memory_budget_bytes=pcfg.memory_budget_bytes, device=dev,
                    progress=progress, database_name=str(database)), runner=runner, store=store)
                laps.lap("filter")
                if runner.started:  # the walk's workers decode their own images: none held through the check
                    read.loader.clear_cache()
                # the global mapper runs here: threads beyond this machine's cores (a remote Dask
                # cluster's slots, --workers 1024) would only be created, never run in parallel
                verdicts, match_check = run_match_check(db, store, rec.match_check, pcfg.source, seed=seed,
                                                        threads=min(runner.slots, os.cpu_count() or 1))
                if rec.match_check.enabled:
                    laps.lap("match_check")
                new_keypoints, refine_stats = run_refine_keypoints(db, read, store, rec, dev, runner, progress,
                                                                   verdicts)
                laps.lap("refine")
                write_stats = run_write(db, read.keypoints, new_keypoints, store.iter_filter_chunks(), pcfg, verdicts)
                laps.lap("write")
            if pcfg.verify:
                run_reverify(work_db)
                laps.lap("verify")
            summary = RefineSummary.from_stages(
                output=database if wc.in_place else wc.output,  # in place: the user's path (a symlink stays one)
                database=database, backup=wc.backup, recipe=rec, device=dev, seed=seed, runner=str(runner.kind),
                resumed=resumed, read=read_stats, filtered=filter_stats, refine=refine_stats,
                write=write_stats, seconds=laps.total(), match_check=match_check)
            if json_path:  # written beside its target now, renamed onto it with the commit
                wc.stage_side_file(json_path, json.dumps(summary.to_dict(), indent=2) + "\n")
            wc.commit()
    except sqlite3.Error as exc:  # a full disk is the working copy's one-line error already
        raise RunFailed(f"SQLite error while writing the copy of {database} ({exc}); {database} is "
                        "unchanged and the working files were removed") from None
    return summary


def _check_writable_file(path: Path, label: str) -> None:
    """Refuse, before any work, an output whose folder is missing or read-only (a character device
    such as ``/dev/stdout`` is written through). UserError names the option and path."""
    from ..adapters.staged_write import CHARACTER_DEVICE, output_kind, write_target

    if output_kind(path) == CHARACTER_DEVICE:
        return
    target = write_target(path)
    via = f" (the target of the symbolic link {path})" if target != path else ""
    if target.is_dir():
        raise UserError(f"{label} {path} is a folder; give a file name")
    if not target.parent.is_dir():
        raise UserError(f"{label} folder does not exist: {target.parent}{via}")
    if not os.access(target.parent, os.W_OK | os.X_OK):
        raise UserError(f"{label} {target}{via}: cannot write in {target.parent} (read-only folder)")


def _refuse_inside_run_folder(path: Path, folder: Path) -> None:
    """Refuse ``--json`` inside the run folder, which is removed after the commit (UserError)."""
    from ..adapters.paths import resolve

    if resolve(folder) in resolve(path).parents:
        raise UserError(f"--json {path} is inside the run folder {folder}, which is removed when the run ends; "
                        "choose a path outside it")


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
