"""``refine_database``: filter and refine the matches of a COLMAP database, safely.

Data flow (one stage after the other)::

    safe working copy -> read pairs -> filter each pair (MOP / MOP+MiHo, parallel)
      -> track-consistent NCC refinement -> write back (keypoints, matches,
      two_view_geometries) -> optional COLMAP re-verification -> atomic replace

The input database is never opened for writing; see :mod:`colmap_miho.adapters.safety`.

Parallelism (see :mod:`colmap_miho.pipeline.stages`): pairs are filtered, and whole tracks
refined, in ``spawn``-ed worker processes with one thread each. Scripts that call
:func:`refine_database` with ``workers > 1`` need the usual ``if __name__ == "__main__":`` guard.
All coordinates handled here are colmap-miho's (integer = pixel centre); the conversion to
COLMAP's happens inside :mod:`colmap_miho.adapters.database`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..enums import Device, MatchSource
from ..errors import DatabaseError, UserError
from ..adapters.database import ColmapDatabase, validate_database
from ..adapters.images import ImageLoader
from ..adapters.safety import WorkingCopy, check_database_path
from .stages import run_filter_stage, run_refine_stage

if TYPE_CHECKING:  # recipe.py imports this package's config: import it lazily
    from ..recipe import Recipe

log = logging.getLogger(__name__)

#: Test hook: when set to a file path, the write stage creates that file and then sleeps,
#: so that a test can kill the process in the middle of writing.
PAUSE_AT_WRITE_ENV = "COLMAP_MIHO_DEBUG_PAUSE_AT_WRITE"
#: Below this many pairs to filter per worker, filtering runs in this process (starting a
#: worker process costs seconds: it imports torch).
MIN_PAIRS_PER_WORKER = 4


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
            filtered = run_filter_stage(db, to_filter, keypoints, pcfg.source, fcfg, seed=seed,
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
                # every other match that stays in the output joins the tracks (never refines)
                unrefined = {(p.image_id1, p.image_id2): db.matches(p.image_id1, p.image_id2,
                                                                    pcfg.source)
                             for p in pairs if p.num_matches < pcfg.min_matches}
                unrefined.update({k: m if not r.success else m[np.asarray(r.inliers, bool)]
                                  for k, (m, r) in filtered.items() if k not in usable})
                new_keypoints, stats, refine_workers = run_refine_stage(
                    loader, keypoints, usable, affines, ncfg, rec.tracks, unrefined=unrefined,
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
