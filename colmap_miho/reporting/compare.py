"""Baseline vs colmap-miho side by side: evaluate both mapped sides with the same pairs and ground
truth, and write ``compare.md``, ``compare.json``, ``report.html`` and ``plots/``. The databases are
only read through copies."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .tables import comparison_markdown, comparison_rows, format_value, table_rows

__all__ = ["CompareResult", "comparison_markdown", "comparison_rows", "evaluate_side", "format_comparison",
           "gt_intrinsics", "match_changes", "table_rows", "write_comparison"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CompareResult:
    """Paths and numbers of one comparison: the folder, both sides' report dicts (empty
    ``reconstruction`` when mapping failed), the refine summary, the table files and plots."""

    output: Path
    baseline: dict
    refined: dict
    refine: dict
    markdown: Path
    json: Path
    plots: list[Path] = field(default_factory=list)


@dataclass(frozen=True, kw_only=True)
class Evaluation:
    """What both sides are scored against: ``gt`` (None: statistics only), ``pairs`` for the
    two-view AUCs (the same for both sides), the protocols' ``seed`` and the AUC ``thresholds`` in
    degrees."""

    gt: Path | None = None
    pairs: object = None
    seed: int = 0
    thresholds: object = None


# --------------------------------------------------------------------------- known cameras
def gt_intrinsics(gt: str | Path) -> dict:
    """A GT model's cameras by image name (COLMAP's pixel convention), for ``run_mapping(intrinsics=...)``."""
    from ..adapters.cameras import CameraIntrinsics
    from .gt_model import load_reconstruction

    rec = load_reconstruction(gt)
    out = {}
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        out[image.name] = CameraIntrinsics(model=cam.model.name, params=tuple(float(v) for v in cam.params),
                                           width=int(cam.width), height=int(cam.height))
    return out


# --------------------------------------------------------------------------- database diffs
def match_changes(baseline_db: str | Path, refined_db: str | Path) -> dict:
    """Per-pair verified match counts before and after (keys :func:`~.pair_labels.pair_label`) and
    the pixel displacements of the keypoints that moved; images by name, keypoints by index."""
    from ..adapters.database import ColmapDatabase
    from ..adapters.safety import read_copy
    from .pair_labels import pair_label

    out: dict = {}
    kps: dict[str, dict[str, np.ndarray]] = {}
    from ..adapters.staged_write import private_tempdir

    with private_tempdir("colmap_miho_cmp_") as tmp:  # removed by the next run after a kill -9
        for tag, src in (("before", Path(baseline_db)), ("after", Path(refined_db))):
            copy = Path(tmp) / f"{tag}.db"
            read_copy(src, copy)  # refuses a database in use or with a hot journal
            with ColmapDatabase(copy) as db:
                names = {r.image_id: r.name for r in db.images()}
                out[f"matches_{tag}"] = {
                    pair_label(names[p.image_id1], names[p.image_id2]): int(p.num_matches)
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


def _epipolar_flips(databases: tuple[Path, Path], gt: str | Path) -> dict:
    """The refined matches turned wrong / right under GT against the baseline's; empty without GT."""
    from .gt_model import load_gt_poses
    from .report import database_epipolar_flips, read_database_inliers

    try:
        poses = load_gt_poses(gt)
    except (OSError, ValueError) as exc:
        log.info("turned-wrong matches skipped: %s", exc)
        return {}
    return database_epipolar_flips(read_database_inliers(databases[0]), read_database_inliers(databases[1]), poses)


# --------------------------------------------------------------------------- compare steps
def _curves(baseline: dict, refined: dict) -> dict:
    def errs(rep, key):
        return [p.get(key) for p in rep.get("pairs", []) if key in p]

    def label(tag, rep, sec):
        a = rep.get(sec)
        if not a:
            return tag
        return f"{tag}  AUC@5/10/20 " + "/".join(format_value(a.get(k), "%") for k in ("auc5", "auc10", "auc20"))

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
    """PLY files, density/outlier figures and a picture of each side's cloud; failures logged, never fatal."""
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


def _evaluate(model_ok: bool, model: Path, database: Path | None, gt, pairs, seed: int, thresholds) -> dict:
    from .report import build_report, json_safe

    if not model_ok:
        # the database's own sections (two-view AUCs, keypoint accuracy) need no model
        rep = (json_safe(build_report(database=database, gt=gt, pairs=pairs, seed=seed, thresholds=thresholds))
               if gt is not None and database is not None else {})
        return {**rep, "reconstruction": {}, "mapping_failed": True}
    return json_safe(build_report(model, database=database if gt is not None else None, gt=gt, pairs=pairs,
                                  seed=seed, thresholds=thresholds))


def evaluate_side(runs: list, database: Path, gt, pairs, seed: int, thresholds=None) -> dict:
    """One side's report: run 0 in full, its ``mapping`` summary, and a ``repeats`` section for several runs."""
    from .repeats import run_row, summarise_runs

    first = runs[0]
    report = _evaluate(first.success, first.output, database, gt, pairs, seed, thresholds)
    report["mapping"] = first.to_dict()
    if len(runs) > 1:
        rows = [run_row(report, first.seed, first.success)]
        for res in runs[1:]:
            rep = _evaluate(res.success, res.output, None, gt, pairs, seed, thresholds)
            rows.append(run_row(rep, res.seed, res.success))
        for row, res in zip(rows, runs, strict=True):
            row["mapping"] = res.to_dict()
        report["repeats"] = summarise_runs(rows)
    return report


def _write_plots(output: Path, baseline: dict, refined: dict, changes: dict) -> list[Path]:
    """The comparison's figures; one that fails is logged and skipped."""
    from . import plots

    plot_files: list[Path] = []

    def draw(name: str, make) -> None:
        try:
            plot_files.append(make(output / "plots" / f"{name}.png"))
        except (RuntimeError, ValueError, OSError, ArithmeticError, LookupError, TypeError) as exc:
            log.warning("figure %s skipped: %s", name, " ".join(str(exc).split()) or type(exc).__name__)

    curves = _curves(baseline, refined)
    if curves:
        draw("pose_error_curves", lambda path: plots.plot_pose_error_curves(curves, path))
    draw("keypoint_displacement", lambda path: plots.plot_displacement_histogram(changes["displacements"], path))
    draw("matches_per_pair", lambda path: plots.plot_matches_per_pair(changes["matches_before"],
                                                                      changes["matches_after"], path))
    return plot_files


def _write_tables(output: Path, baseline: dict, refined: dict, refine: dict, changes: dict, clouds: dict,
                  plot_files: list[Path]) -> tuple[Path, Path]:
    """compare.md and compare.json (the JSON without the per-pair rows)."""
    from ..adapters.staged_write import write_text_atomic
    from .report import write_report_json

    md = output / "compare.md"
    write_text_atomic(md, comparison_markdown(baseline, refined, refine))
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
    return md, write_report_json(summary_json, output / "compare.json")


def write_comparison(output: Path, base_runs: list, ref_runs: list, *, databases: tuple[Path, Path],
                     refine: dict, evaluation: Evaluation) -> CompareResult:
    """Evaluate both sides (run 0 in full) and write their reports, the plots and the tables."""
    from .html_report import write_comparison_html
    from .report import write_report_json

    ev = evaluation
    pairs = ev.pairs
    if ev.gt is not None and pairs is None:
        from .gt_model import load_gt_poses
        from .report import default_eval_pairs

        pairs, _ = default_eval_pairs(ev.gt, load_gt_poses(ev.gt))
    baseline = evaluate_side(base_runs, databases[0], ev.gt, pairs, ev.seed, ev.thresholds)
    refined = evaluate_side(ref_runs, databases[1], ev.gt, pairs, ev.seed, ev.thresholds)
    if ev.gt is not None:
        refined["epipolar_flips"] = _epipolar_flips(databases, ev.gt)
    changes = match_changes(*databases)

    def publish(plot_files: list[Path], clouds: dict) -> tuple[Path, Path]:
        for tag, rep in (("baseline", baseline), ("refined", refined)):
            if tag in clouds:
                rep["pointcloud"] = clouds[tag]
            write_report_json(rep, output / tag / "report.json")
        tables = _write_tables(output, baseline, refined, refine, changes, clouds, plot_files)
        write_comparison_html(output / "report.html", baseline, refined, refine, changes)
        return tables

    # the tables first: a figure that fails costs only itself
    md, js = publish([], {})
    plot_files = _write_plots(output, baseline, refined, changes)
    clouds = _point_clouds(output, base_runs[0], ref_runs[0], plot_files)
    if plot_files or clouds:
        md, js = publish(plot_files, clouds)
    return CompareResult(output=output, baseline=baseline, refined=refined, refine=refine, markdown=md, json=js,
                         plots=plot_files)


def format_comparison(result: CompareResult) -> str:
    """Terminal text: the side-by-side table and where the files are."""
    rows = comparison_rows(result.baseline, result.refined)
    w = max((len(r[0]) for r in rows), default=10) + 2
    cw = max([12, *(len(c) + 2 for r in rows for c in r[1:])])
    lines = [f"{'metric':<{w}}{'baseline':>{cw}}{'colmap-miho':>{cw}}"]
    lines += [f"{a:<{w}}{b:>{cw}}{c:>{cw}}" for a, b, c in rows]
    runs = result.baseline.get("repeats", {}).get("num_runs")
    if runs:
        lines += ["", f"mapping figures: median [min-max] of {runs} runs per side"]
    mc = (result.refine or {}).get("match_check")
    if mc:
        from ..terminal import printable
        from .html_report import match_check_note

        lines += ["", printable(match_check_note(mc))]
    lines += ["", f"table:  {result.markdown}", f"json:   {result.json}"]
    if (result.output / "report.html").is_file():
        lines.append(f"report: {result.output / 'report.html'}  (open in a browser)")
    lines += [f"plot:   {p}" for p in result.plots]
    return "\n".join(lines)


