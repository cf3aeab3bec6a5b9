"""Baseline vs colmap-miho on one database, and the whole job from a folder of images.

:func:`compare_databases` maps the database as it is (baseline) and after
:func:`colmap_miho.pipeline.refine_database`, evaluates both with the same pairs and ground
truth, and writes side by side::

    OUTPUT/
      baseline/model/  baseline/report.json
      refined/database.db  refined/refine.json  refined/model/  refined/report.json
      compare.md  compare.json
      plots/pose_error_curves.png  plots/keypoint_displacement.png  plots/matches_per_pair.png

:func:`run_from_images` extracts SIFT features and matches them exhaustively (pycolmap, CPU)
into ``OUTPUT/database.db``, then refines, maps and reports, or runs the comparison.
The input database is never modified (everything reads copies).
"""

from __future__ import annotations

import logging
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import RunFailed
from .keypoint_accuracy import EPIPOLAR_THRESHOLD_PX, TRACK_THRESHOLD_PX

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CompareResult:
    """Paths and numbers of one comparison.

    Attributes:
        output: the comparison folder.
        baseline, refined: report dicts (see :func:`colmap_miho.reporting.report.build_report`);
            an empty ``reconstruction`` when mapping failed.
        refine: ``RefineSummary.to_dict()``.
        markdown, json: the side-by-side table files.
        plots: the PNG files written.
    """

    output: Path
    baseline: dict
    refined: dict
    refine: dict
    markdown: Path
    json: Path
    plots: list[Path] = field(default_factory=list)


# --------------------------------------------------------------------------- database diffs
def match_changes(baseline_db: str | Path, refined_db: str | Path) -> dict:
    """Per-pair verified match counts and keypoint displacements between two databases.

    Both databases are read through temporary copies. Images are matched by name; keypoint
    rows by index (refinement moves keypoints in place).

    Returns:
        ``{"matches_before": {"a|b": n}, "matches_after": {"a|b": n},
        "displacements": float64 (K,) pixel distances of the keypoints that moved}``.
    """
    from ..adapters.database import ColmapDatabase
    from ..adapters.safety import read_copy

    out: dict = {}
    kps: dict[str, dict[str, np.ndarray]] = {}
    with tempfile.TemporaryDirectory(prefix="colmap_miho_cmp_") as tmp:
        for tag, src in (("before", Path(baseline_db)), ("after", Path(refined_db))):
            copy = Path(tmp) / f"{tag}.db"
            read_copy(src, copy)  # refuses a database in use or with a hot journal
            with ColmapDatabase(copy) as db:
                names = {r.image_id: r.name for r in db.images()}
                out[f"matches_{tag}"] = {
                    "|".join(sorted((names[p.image_id1], names[p.image_id2]))): int(p.num_matches)
                    for p in db.pairs("verified")
                }
                kps[tag] = {names[i]: db.keypoints(i) for i in names}
    disp = []
    for name, k0 in kps["before"].items():
        k1 = kps["after"].get(name)
        if k1 is None or k1.shape != k0.shape:
            continue
        d = np.linalg.norm(k1 - k0, axis=1)
        disp.append(d[d > 1e-6])
    out["displacements"] = np.concatenate(disp) if disp else np.zeros(0)
    return out


# --------------------------------------------------------------------------- tables
_ROWS = [
    ("registered images", ("reconstruction", "num_reg_images"), "d"),
    ("3D points", ("reconstruction", "num_points3D"), "d"),
    ("observations", ("reconstruction", "num_observations"), "d"),
    ("mean track length", ("reconstruction", "mean_track_length"), ".2f"),
    ("mean reprojection error (px)", ("reconstruction", "mean_reprojection_error"), ".3f"),
    ("model pose AUC@5 (%)", ("model_pose_auc", "auc5"), "%"),
    ("model pose AUC@10 (%)", ("model_pose_auc", "auc10"), "%"),
    ("model pose AUC@20 (%)", ("model_pose_auc", "auc20"), "%"),
    ("model pose mAA (%)", ("model_pose_auc", "maa"), "%"),
    ("rotation error median (deg)", ("absolute", "rotation_error_deg", "median"), ".3f"),
    ("centre error / camera spread (%)", ("absolute", "center_error_rel"), "%2"),
    ("sparse-cloud outliers (%)", ("pointcloud", "outlier_share"), "%"),
    ("two-view E AUC@5 (%)", ("two_view_pose_auc_E", "auc5"), "%"),
    ("two-view E AUC@10 (%)", ("two_view_pose_auc_E", "auc10"), "%"),
    ("two-view E AUC@20 (%)", ("two_view_pose_auc_E", "auc20"), "%"),
    ("two-view F AUC@5 (%)", ("two_view_pose_auc_F", "auc5"), "%"),
    ("two-view F AUC@10 (%)", ("two_view_pose_auc_F", "auc10"), "%"),
    ("two-view F AUC@20 (%)", ("two_view_pose_auc_F", "auc20"), "%"),
    # keypoint accuracy under GT geometry (colmap_miho.reporting.keypoint_accuracy)
    ("GT track residual median (px)", ("keypoint_accuracy", "residual_median_px"), ".3f"),
    ("GT track residual mean (px)", ("keypoint_accuracy", "residual_mean_px"), ".3f"),
    ("GT track residual p90 (px)", ("keypoint_accuracy", "residual_p90_px"), ".3f"),
    ("GT tracks measured", ("keypoint_accuracy", "num_measured_tracks"), "d"),
    (f"wrong tracks > {TRACK_THRESHOLD_PX:g} px (%)", ("keypoint_accuracy", "wrong_track_share"), "%"),
    ("conflicting tracks", ("keypoint_accuracy", "num_conflicting_tracks"), "d"),
    ("epipolar distance median (px)", ("keypoint_accuracy", "epipolar_median_px"), ".3f"),
    (f"epipolar distance > {EPIPOLAR_THRESHOLD_PX:g} px (%)", ("keypoint_accuracy", "epipolar_share_above"), "%"),
]


def _get(d: dict, path: tuple):
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _fmt(v, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if spec == "%":
        return f"{100 * v:.1f}"
    if spec == "%2":
        return f"{100 * v:.2f}"
    return format(v, spec)


def comparison_rows(baseline: dict, refined: dict) -> list[tuple[str, str, str]]:
    """(metric, baseline, refined) text rows for every metric present in either report."""
    rows = []
    for label, path, spec in _ROWS:
        b, r = _get(baseline, path), _get(refined, path)
        if b is None and r is None:
            continue
        rows.append((label, _fmt(b, spec), _fmt(r, spec)))
    return rows


def comparison_markdown(baseline: dict, refined: dict, refine: dict, title: str = "colmap-miho comparison") -> str:
    """A markdown document: the side-by-side table plus the refine counters."""
    lines = [f"# {title}", "", "| metric | baseline | colmap-miho |", "|---|---:|---:|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in comparison_rows(baseline, refined)]
    if refine:
        lines += [
            "", f"Recipe `{refine.get('recipe', '')}`: {refine.get('pairs_filtered', 0)} pairs filtered, "
            f"{refine.get('matches_kept', 0)} of {refine.get('matches_in', 0)} matches kept, "
            f"{refine.get('keypoints_moved', 0)} keypoints moved (median "
            f"{refine.get('median_displacement_px', 0.0):.2f} px), "
            f"{refine.get('seconds', {}).get('total', float('nan')):.1f} s.",
        ]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- compare
def _evaluate(model_ok: bool, model: Path, database: Path, gt, pairs, seed: int) -> dict:
    from .report import build_report, json_safe

    if not model_ok:
        # the database's own sections (two-view AUCs, keypoint accuracy) need no model
        rep = json_safe(build_report(database=database, gt=gt, pairs=pairs, seed=seed)) if gt is not None else {}
        return {**rep, "reconstruction": {}, "mapping_failed": True}
    return json_safe(build_report(model, database=database if gt is not None else None, gt=gt, pairs=pairs, seed=seed))


def _curves(baseline: dict, refined: dict) -> dict:
    def errs(rep, key):
        return [p.get(key) for p in rep.get("pairs", []) if key in p]

    def label(tag, rep, sec):
        a = rep.get(sec)
        if not a:
            return tag
        return f"{tag}  AUC@5/10/20 " + "/".join(_fmt(a.get(k), "%") for k in ("auc5", "auc10", "auc20"))

    curves = {}
    for metric, key, sec in (("model poses (all GT pairs)", "model", "model_pose_auc"),
                             ("two-view E", "E", "two_view_pose_auc_E"),
                             ("two-view F (+MAGSAC)", "F", "two_view_pose_auc_F")):
        c = {}
        for tag, rep in (("baseline", baseline), ("refined", refined)):
            e = errs(rep, key)
            if e:
                c[label(tag, rep, sec)] = e
        if c:
            curves[metric] = c
    return curves


def _point_clouds(output: Path, base_map, ref_map, plot_files: list) -> dict:
    """PLY files, density/outlier figures and a picture of each side's sparse cloud.

    Uses :mod:`colmap_miho.reporting.pointcloud` (open3d optional: it falls back to scipy and
    matplotlib); any failure there is logged and skipped, never fatal.
    """
    try:
        from . import pointcloud as pc
    except ImportError as exc:  # pragma: no cover - module missing in a partial install
        log.info("point-cloud figures skipped: %s", exc)
        return {}
    out: dict = {}
    for tag, res in (("baseline", base_map), ("refined", ref_map)):
        if not res.success or res.reconstruction is None:
            continue
        try:
            ply = pc.export_ply(res.reconstruction, output / tag / "points.ply")
            xyz, rgb = pc.reconstruction_points(res.reconstruction)
            out[tag] = {"ply": str(ply), **pc.cloud_figures(xyz)}
            png = output / "plots" / f"points_{tag}.png"
            pc.render_cloud_png(xyz, rgb, png, title=f"{tag}: {len(xyz)} points")
            plot_files.append(png)
        except (RuntimeError, ValueError, OSError) as exc:
            log.info("point-cloud figures for %s skipped: %s", tag, exc)
    return out


def compare_databases(
    database: str | Path,
    image_dir: str | Path,
    output: str | Path,
    *,
    gt: str | Path | None = None,
    pairs=None,
    recipe=None,
    mapper: str = "incremental",
    seed: int = 0,
    workers: int | None = None,
    device: str = "auto",
    progress: bool = False,
    verbose: bool = False,
) -> CompareResult:
    """Map and evaluate ``database`` as it is and after ``refine_database``; write tables/plots.

    Args:
        database: COLMAP database (never modified).
        image_dir: its image folder.
        output: comparison folder (created; files in it are replaced).
        gt: GT COLMAP model folder (or dataset folder with ``gt_model/``); without it only
            reconstruction statistics are compared.
        pairs: pairs for the two-view AUCs (list or file); default: the dataset's
            ``pairs_with_gt.txt`` if present, else all GT pairs. Both sides use the same pairs.
        recipe: Recipe, recipe name or TOML path for ``refine_database``.
        mapper, seed: mapping options (same for both sides).
        workers, device: ``refine_database`` options.
        progress, verbose: bars and COLMAP's log on the terminal.

    Returns:
        :class:`CompareResult`.
    """
    from . import plots
    from .report import write_report_json
    from ..sfm import run_mapping
    from ..pipeline.refine import refine_database

    output = Path(output)
    (output / "baseline").mkdir(parents=True, exist_ok=True)
    (output / "refined").mkdir(parents=True, exist_ok=True)
    (output / "plots").mkdir(exist_ok=True)
    database, image_dir = Path(database), Path(image_dir)

    log.info("baseline: mapping the database as it is")
    base_map = run_mapping(database, image_dir, output / "baseline" / "model", mapper=mapper, seed=seed,
                           progress=progress, verbose=verbose)
    log.info("refining the matches (recipe %s)", getattr(recipe, "name", recipe) or "default")
    refined_db = output / "refined" / "database.db"
    summary = refine_database(database, image_dir, refined_db, recipe=recipe, overwrite=True, workers=workers,
                              device=device, seed=seed, progress=progress,
                              json_path=output / "refined" / "refine.json")
    refine = summary.to_dict()
    log.info("refined: mapping the refined database")
    ref_map = run_mapping(summary.output, image_dir, output / "refined" / "model", mapper=mapper, seed=seed,
                          progress=progress, verbose=verbose)
    if not base_map.success and not ref_map.success:
        raise RunFailed("mapping failed on both the baseline and the refined database")

    if gt is not None and pairs is None:
        from .gt_model import load_gt_poses
        from .report import default_eval_pairs

        pairs, _ = default_eval_pairs(gt, load_gt_poses(gt))
    baseline = _evaluate(base_map.success, base_map.output, database, gt, pairs, seed)
    refined = _evaluate(ref_map.success, ref_map.output, summary.output, gt, pairs, seed)
    baseline["mapping"] = base_map.to_dict()
    refined["mapping"] = ref_map.to_dict()

    changes = match_changes(database, summary.output)
    plot_files = []
    curves = _curves(baseline, refined)
    if curves:
        plot_files.append(plots.plot_pose_error_curves(curves, output / "plots" / "pose_error_curves.png"))
    plot_files.append(plots.plot_displacement_histogram(changes["displacements"],
                                                        output / "plots" / "keypoint_displacement.png"))
    plot_files.append(plots.plot_matches_per_pair(changes["matches_before"], changes["matches_after"],
                                                  output / "plots" / "matches_per_pair.png"))

    clouds = _point_clouds(output, base_map, ref_map, plot_files)
    for tag, rep in (("baseline", baseline), ("refined", refined)):
        if tag in clouds:
            rep["pointcloud"] = clouds[tag]
        write_report_json(rep, output / tag / "report.json")
    md = output / "compare.md"
    md.write_text(comparison_markdown(baseline, refined, refine), encoding="utf-8")
    disp = changes["displacements"]
    summary_json = {
        "baseline": {k: v for k, v in baseline.items() if k != "pairs"},
        "refined": {k: v for k, v in refined.items() if k != "pairs"},
        "refine": refine,
        "matches_per_pair": {"baseline": changes["matches_before"], "refined": changes["matches_after"]},
        "keypoint_displacement_px": {
            "count": int(disp.size),
            "median": float(np.median(disp)) if disp.size else None,
            "p90": float(np.quantile(disp, 0.9)) if disp.size else None,
            "max": float(disp.max()) if disp.size else None,
        },
        "pointcloud": clouds,
        "rows": [{"metric": a, "baseline": b, "refined": c} for a, b, c in comparison_rows(baseline, refined)],
        "plots": [str(p) for p in plot_files],
    }
    js = write_report_json(summary_json, output / "compare.json")
    return CompareResult(output=output, baseline=baseline, refined=refined, refine=refine, markdown=md, json=js,
                         plots=plot_files)


def format_comparison(result: CompareResult) -> str:
    """Terminal text: the side-by-side table and where the files are."""
    rows = comparison_rows(result.baseline, result.refined)
    w = max((len(r[0]) for r in rows), default=10) + 2
    lines = [f"{'metric':<{w}}{'baseline':>12}{'colmap-miho':>14}"]
    lines += [f"{a:<{w}}{b:>12}{c:>14}" for a, b, c in rows]
    lines += ["", f"table:  {result.markdown}", f"json:   {result.json}"]
    lines += [f"plot:   {p}" for p in result.plots]
    return "\n".join(lines)


# --------------------------------------------------------------------------- from images
def run_from_images(
    image_dir: str | Path,
    output: str | Path,
    *,
    gt: str | Path | None = None,
    recipe=None,
    compare: bool = False,
    camera_mode: str = "single",
    camera_model: str = "SIMPLE_RADIAL",
    camera_params: str = "",
    max_features: int = 8192,
    mapper: str = "incremental",
    seed: int = 0,
    workers: int | None = None,
    device: str = "auto",
    progress: bool = False,
    verbose: bool = False,
) -> dict:
    """The whole job from a folder of images: SIFT + exhaustive matching, refine, map, report.

    Writes ``OUTPUT/database.db`` (COLMAP's features and matches, kept as the baseline input).
    Without ``compare``: ``OUTPUT/refined/{database.db, refine.json, model/}`` and
    ``OUTPUT/report.json``. With ``compare``: :func:`compare_databases` into ``OUTPUT``.

    Returns:
        ``{"database", "features", "report" | "compare"}`` (a JSON-ready dict; with compare
        the :class:`CompareResult` is under ``"result"`` too).

    Raises:
        RunFailed: extraction found < 2 images, or mapping registered nothing.
    """
    from .report import build_report, write_report_json
    from ..sfm import extract_and_match, require_success, run_mapping
    from ..pipeline.refine import refine_database

    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    database = output / "database.db"
    if database.exists():
        log.info("reusing the features and matches in %s", database)
        features = {"reused": True}
    else:
        features = extract_and_match(image_dir, database, camera_mode=camera_mode, camera_model=camera_model,
                                     camera_params=camera_params, max_features=max_features, verbose=verbose)
    out: dict = {"database": str(database), "features": features}
    if compare:
        res = compare_databases(database, image_dir, output, gt=gt, recipe=recipe, mapper=mapper, seed=seed,
                                workers=workers, device=device, progress=progress, verbose=verbose)
        out["compare"] = str(res.json)
        out["result"] = res
        return out
    (output / "refined").mkdir(exist_ok=True)
    summary = refine_database(database, image_dir, output / "refined" / "database.db", recipe=recipe,
                              overwrite=True, workers=workers, device=device, seed=seed, progress=progress,
                              json_path=output / "refined" / "refine.json")
    res = require_success(run_mapping(summary.output, image_dir, output / "refined" / "model", mapper=mapper,
                                      seed=seed, progress=progress, verbose=verbose))
    report = build_report(res.output, reconstruction=res.reconstruction,
                          database=summary.output if gt is not None else None, gt=gt, seed=seed)
    report["refine"] = summary.to_dict()
    report["mapping"] = res.to_dict()
    out["report"] = str(write_report_json(report, output / "report.json"))
    out["report_dict"] = report
    return out

