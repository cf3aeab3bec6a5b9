"""The whole jobs of the ``run``, ``compare`` and ``demo`` commands, built on
:func:`~colmap_miho.pipeline.refine_job.refine_database`.

:func:`compare_databases` maps a database as it is and after refinement, ``repeats`` times each, and
writes the comparison (``baseline/``, ``refined/``, ``compare.md``, ``report.html``);
:func:`run_from_images` extracts and matches SIFT into ``OUTPUT/database.db`` first. The input
database is never modified."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from ..adapters.paths import check_distinct, comparison_paths
from ..arguments import check_integer, check_paths, check_seed, check_workers
from ..enums import CameraMode, Device, Mapper
from ..errors import InvalidInput, RunFailed
from ..kernel_cache import compile_in_background, families_for
from ..recipe import Recipe, load_recipe
from ..reporting.compare import CompareResult, Evaluation, gt_intrinsics, write_comparison
from ..seeds import mapping_seed
from ..sfm import MappingConfig, parse_camera_params
from ..validation import OPTION_BOUNDS
from .refine_job import refine_database
from .summary import RefineSummary

log = logging.getLogger(__name__)

__all__ = ["ExtractionOptions", "JobOptions", "compare_databases", "map_repeats", "run_from_images"]


@dataclass(frozen=True, kw_only=True)
class JobOptions:
    """How a whole job maps, evaluates and runs.

    Attributes:
        mapper: when given, replaces the recipe's ``mapping.mapper``.
        seed: the run's root seed; every stage's seed derives from it (:mod:`colmap_miho.seeds`).
        repeats: mapping runs per side, seeds ``seed, seed + 1, ...``; with more than one the
            reports get a ``repeats`` section (per-run rows, median, min, max).
        gt_cameras: write the GT model's intrinsics into the mapped copies (needs ``gt``;
            combine with ``mapping.refine_intrinsics = "none"`` to keep them).
        thresholds: pose-AUC thresholds in degrees (None: 0.5/1/2/5/10/20).
        workers, device: ``refine_database`` options.
        progress, verbose: bars (one per mapping run) and COLMAP's log on the terminal.
    """

    mapper: Mapper | None = None
    seed: int = 0
    repeats: int = 1
    gt_cameras: bool = False
    thresholds: Sequence[float] | None = None
    workers: int | None = None
    device: Device = Device.AUTO
    progress: bool = False
    verbose: bool = False

    def __post_init__(self) -> None:
        check_seed(self.seed)
        check_workers(self.workers)
        check_integer("repeats", self.repeats, OPTION_BOUNDS["repeats"])
        if self.mapper is not None:
            object.__setattr__(self, "mapper", Mapper.parse(self.mapper, "mapper"))
        object.__setattr__(self, "device", Device.parse(self.device, "device"))


@dataclass(frozen=True, kw_only=True)
class ExtractionOptions:
    """SIFT extraction of :func:`run_from_images`; the camera is a prior only.

    Attributes:
        camera_mode: "single", "per_folder" or "per_image".
        camera_model, camera_params: COLMAP model name and comma-separated parameters ("" =
          estimated from the image size).
        max_features: SIFT features per image.
    """

    camera_mode: CameraMode = CameraMode.SINGLE
    camera_model: str = "SIMPLE_RADIAL"
    camera_params: str = ""
    max_features: int = 8192

    def __post_init__(self) -> None:
        object.__setattr__(self, "camera_mode", CameraMode.parse(self.camera_mode, "camera_mode"))
        check_integer("max_features", self.max_features, OPTION_BOUNDS["max_features"])
        parse_camera_params(str(self.camera_model), str(self.camera_params))  # before any folder is made


def _as_recipe(recipe: Recipe | str | None) -> Recipe:
    return recipe if isinstance(recipe, Recipe) else load_recipe(recipe)


def _job_recipe(recipe: Recipe | str | None, opts: JobOptions, gt: str | Path | None
                ) -> tuple[Recipe, MappingConfig]:
    """The job's recipe and mapping config with ``opts``' overrides; InvalidInput for GT cameras without GT."""
    if opts.gt_cameras and gt is None:
        raise InvalidInput("taking the cameras from the GT needs --gt")
    rec = _as_recipe(recipe)
    return rec, _mapping_config(rec, opts)


def _mapping_config(recipe: Recipe, opts: JobOptions) -> MappingConfig:
    """The recipe's ``mapping`` config with the ``mapper`` override applied."""
    cfg = recipe.mapping
    if opts.mapper is not None:
        cfg = replace(cfg, mapper=opts.mapper)
    return cfg


def map_repeats(database: Path, image_dir: Path, folder: Path, mapping: MappingConfig, *, seed: int = 0,
                repeats: int = 1, intrinsics: dict | None = None, tag: str = "", progress: bool = False,
                verbose: bool = False) -> list:
    """Map ``database`` ``repeats`` times, the k-th with :func:`~colmap_miho.seeds.mapping_seed`
    (``seed``, k).

    Run 0 writes ``folder/model`` (the model the report and plots use), run k >= 1
    ``folder/runs/seed<S>/model``. Returns the ``MappingResult`` of each run.
    """
    from ..sfm import run_mapping

    if repeats < 1:
        raise InvalidInput(f"repeats must be >= 1, got {repeats}")
    results = []
    for k in range(repeats):
        run_seed = mapping_seed(seed, k)
        out = folder / "model" if k == 0 else folder / "runs" / f"seed{run_seed}" / "model"
        label = f"{tag} run {k + 1}/{repeats}" if repeats > 1 else f"{tag} mapping".strip()
        log.info("%s: mapping (seed %d)", tag or "mapping", run_seed)
        results.append(run_mapping(database, image_dir, out, mapping, seed=run_seed, intrinsics=intrinsics,
                                   progress=progress, label=label, verbose=verbose))
    return results


def _refine_into(database: Path, image_dir: Path, folder: Path, recipe: Recipe, opts: JobOptions,
                 seed: int) -> RefineSummary:
    """``refine_database`` into ``folder/database.db`` (and ``refine.json``), replacing earlier output."""
    return refine_database(database, image_dir, folder / "database.db", recipe=recipe, overwrite=True,
                           restart=True, workers=opts.workers, device=opts.device, seed=seed,
                           progress=opts.progress, json_path=folder / "refine.json")


def check_compare_inputs(database: str | Path, image_dir: str | Path, gt: str | Path | None) -> None:
    """Check what ``compare`` reads before it maps for minutes: the image folder, the database (on a
    private copy) and the GT model. Raises NotADirectoryError, DatabaseError or InvalidInput."""
    from ..adapters.database import validate_database
    from ..adapters.safety import read_copy
    from ..adapters.staged_write import private_tempdir

    if not Path(image_dir).is_dir():
        raise NotADirectoryError(f"image folder not found: {image_dir}")
    with private_tempdir("colmap_miho_check_") as tmp:
        copy = Path(tmp) / "database.db"
        read_copy(database, copy)
        validate_database(copy, name=database)
    if gt is not None:
        from ..reporting.gt_model import load_gt_poses

        load_gt_poses(gt)


def compare_databases(database: str | Path, image_dir: str | Path, output: str | Path, *,
                      recipe: Recipe | str | None = None, gt: str | Path | None = None, pairs: object = None,
                      options: JobOptions | None = None) -> CompareResult:
    """Map and evaluate ``database`` as it is and after ``refine_database``; write tables and plots.

    ``output``: the comparison folder (created; files in it replaced). ``recipe``: Recipe, name or
    TOML path, for refinement and both sides' mapping. ``gt``: GT model folder (without it only
    reconstruction statistics are compared). ``pairs``: pairs for the two-view AUCs, the same for
    both sides. Returns a :class:`~colmap_miho.reporting.compare.CompareResult`."""
    check_paths(database=database, image_dir=image_dir, output=output, gt=gt, optional=("gt",))
    if pairs is not None and not isinstance(pairs, (str, os.PathLike, list, tuple)):
        raise InvalidInput(f"pairs must be a pairs file or a list of (name1, name2), got {type(pairs).__name__}")
    if options is not None and not isinstance(options, JobOptions):
        raise InvalidInput(f"options must be of type JobOptions, got {type(options).__name__}")
    opts = options or JobOptions()
    rec, mapping = _job_recipe(recipe, opts, gt)
    output = Path(output)
    check_distinct(*comparison_paths(output, database=database, images=image_dir, gt=gt, repeats=opts.repeats,
                                     pairs=pairs if isinstance(pairs, (str, Path)) else None, seed=opts.seed))
    check_compare_inputs(database, image_dir, gt)  # before any folder is made
    compile_in_background(families_for(rec))  # while the baseline maps
    intrinsics = gt_intrinsics(gt) if opts.gt_cameras and gt is not None else None
    for sub in ("baseline", "refined", "plots"):
        (output / sub).mkdir(parents=True, exist_ok=True)
    database, image_dir = Path(database), Path(image_dir)

    def map_side(db: Path, tag: str) -> list:
        return map_repeats(db, image_dir, output / tag, mapping, seed=opts.seed, repeats=opts.repeats,
                           intrinsics=intrinsics, tag=tag, progress=opts.progress, verbose=opts.verbose)

    base_runs = map_side(database, "baseline")
    log.info("refining the matches (recipe %s)", rec.name)
    summary = _refine_into(database, image_dir, output / "refined", rec, opts, opts.seed)
    ref_runs = map_side(summary.output, "refined")
    if not any(r.success for r in base_runs + ref_runs):
        raise RunFailed("mapping failed on both the baseline and the refined database")
    return write_comparison(output, base_runs, ref_runs, databases=(database, summary.output),
                            refine=summary.to_dict(),
                            evaluation=Evaluation(gt=None if gt is None else Path(gt), pairs=pairs,
                                                  seed=opts.seed, thresholds=opts.thresholds))


def run_from_images(image_dir: str | Path, output: str | Path, *, recipe: Recipe | str | None = None,
                    gt: str | Path | None = None, compare: bool = False,
                    extraction: ExtractionOptions | None = None, options: JobOptions | None = None) -> dict:
    """The whole job from a folder of images: SIFT and exhaustive matching, refine, map, report.

    Writes ``OUTPUT/database.db`` (the baseline input), then ``OUTPUT/refined/`` and
    ``OUTPUT/report.json``, or with ``compare`` :func:`compare_databases` into ``OUTPUT``. Returns a
    JSON-ready dict; RunFailed when extraction finds under 2 images or mapping registers nothing."""
    from ..reporting.report import build_report, write_report_json
    from ..sfm import require_success, run_mapping
    from ..sfm.extraction import extract_and_match

    check_paths(image_dir=image_dir, output=output, gt=gt, optional=("gt",))
    for name, value, kind in (("options", options, JobOptions), ("extraction", extraction, ExtractionOptions)):
        if value is not None and not isinstance(value, kind):
            raise InvalidInput(f"{name} must be of type {kind.__name__}, got {type(value).__name__}")
    opts = options or JobOptions()
    ext = extraction or ExtractionOptions()
    rec, mapping = _job_recipe(recipe, opts, gt)
    output = Path(output)
    check_distinct(*comparison_paths(output, images=image_dir, gt=gt, repeats=opts.repeats, seed=opts.seed,
                                     compare=compare))
    output.mkdir(parents=True, exist_ok=True)
    compile_in_background(families_for(rec))  # while the features are extracted and matched
    database = output / "database.db"
    if database.exists():
        log.info("reusing the features and matches in %s", database)
        features: dict = {"reused": True}
    else:
        features = extract_and_match(image_dir, database, camera_mode=ext.camera_mode, camera_model=ext.camera_model,
                                     camera_params=ext.camera_params, max_features=ext.max_features,
                                     verbose=opts.verbose)
    out: dict = {"database": str(database), "features": features}
    if compare:
        res = compare_databases(database, image_dir, output, gt=gt, recipe=rec, options=opts)
        out["compare"] = str(res.json)
        out["result"] = res
        return out
    (output / "refined").mkdir(exist_ok=True)
    summary = _refine_into(database, Path(image_dir), output / "refined", rec, opts, opts.seed)
    res_map = require_success(run_mapping(summary.output, image_dir, output / "refined" / "model", mapping,
                                          seed=mapping_seed(opts.seed),
                                          intrinsics=gt_intrinsics(gt) if opts.gt_cameras and gt is not None
                                          else None, progress=opts.progress, verbose=opts.verbose))
    report = build_report(res_map.output, reconstruction=res_map.reconstruction,
                          database=summary.output if gt is not None else None, gt=gt, seed=opts.seed,
                          thresholds=opts.thresholds)
    report["refine"] = summary.to_dict()
    report["mapping"] = res_map.to_dict()
    out["report"] = str(write_report_json(report, output / "report.json"))
    out["report_dict"] = report
    return out
