"""Baseline vs colmap-miho on the shared scenes mapped with KNOWN cameras, repeated runs.

For each scene and COLMAP matching setting (``default``; ``permissive``: SIFT ratio 0.95, no
cross-check) the database is built once (cached under ``--cache``, the same cache as
``bench_accuracy.py``), refined once with the recipe (cached under ``--work``), and both
databases are mapped ``--repeats`` times (seeds 0, 1, ...) with the GT intrinsics written into
the mapped copy and ``refine_intrinsics=none`` (bundle adjustment keeps them). One row per
scene / setting / side: the median over the runs of the registered images and of the model
pose AUC at 0.5/1/2/5 deg (all GT pairs; in brackets the range over the runs), and the GT
keypoint accuracy of the database's stored inliers (``keypoint_accuracy`` section: track
residual median and wrong-track share), which does not depend on the mapping.

    python benchmarks/bench_known_cameras.py [--data ../shared/data] [--work /tmp/bench_known_cameras]
        [--cache /tmp/bench_accuracy] [--scenes ...] [--settings default permissive]
        [--repeats 3] [--recipe mop_miho_lsm] [--set key=value] [--workers 1] [--threads 1]
        [--refine-intrinsics none] [--json out.json]

``--threads 1`` (default) makes each run deterministic for its seed; the spread then comes
from the seeds alone.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import statistics
import sys
import time
from pathlib import Path

from bench_accuracy import SETTINGS, SHARED_SCENES, build_database

REPO = Path(__file__).resolve().parents[1]
AUCS = (0.5, 1.0, 2.0, 5.0)


def refined_database(db: Path, image_dir: Path, folder: Path, recipe, overrides: list[str], workers: int) -> Path:
    """``refine_database`` output of ``db`` under ``folder``, cached by recipe and overrides."""
    from colmap_miho.pipeline.run import refine_database

    tag = hashlib.sha1(" ".join([recipe.name, *overrides]).encode()).hexdigest()[:8]
    out = folder / f"refined_{recipe.name}_{tag}.db"
    if not out.is_file():
        tmp = out.with_suffix(".tmp.db")
        refine_database(db, image_dir, tmp, recipe=recipe, overwrite=True, restart=True, workers=workers,
                        seed=0)
        tmp.rename(out)
    return out


def map_runs(db: Path, image_dir: Path, gt: Path, folder: Path, repeats: int, mapping, intrinsics) -> list[dict]:
    """Map ``db`` ``repeats`` times (seeds 0..repeats-1); one row of figures per run."""
    from dataclasses import replace

    from colmap_miho.reporting.report import auc_key, build_report
    from colmap_miho.sfm import run_mapping

    rows = []
    for seed in range(repeats):
        res = run_mapping(db, image_dir, folder / f"model_seed{seed}", replace(mapping, seed=seed),
                          intrinsics=intrinsics)
        row = {"seed": seed, "num_reg_images": res.num_reg_images, "num_images": res.num_images,
               "seconds": res.seconds}
        if res.success:
            rep = build_report(reconstruction=res.reconstruction, gt=gt, thresholds=AUCS)
            row.update({auc_key(t): rep["model_pose_auc"][auc_key(t)] for t in AUCS})
            row["mean_reprojection_error"] = rep["reconstruction"]["mean_reprojection_error"]
        else:
            row.update({auc_key(t): 0.0 for t in AUCS})
        rows.append(row)
    return rows


def _median_range(values: list[float], pct: bool) -> str:
    """``median (min-max)``; the range only when it shows at the printed precision."""
    def fmt(v: float) -> str:
        return f"{100.0 * v:.1f}" if pct else f"{v:g}"

    lo, med, hi = fmt(min(values)), fmt(statistics.median(values)), fmt(max(values))
    return med if lo == hi else f"{med} ({lo}-{hi})"


def table(rows: list[dict]) -> str:
    """Markdown table: medians over the runs, ranges in brackets."""
    from colmap_miho.reporting.report import auc_key

    head = ["scene", "setting", "side", "registered", *[f"AUC@{t:g} (%)" for t in AUCS], "GT residual med (px)",
            "wrong tracks (%)"]
    lines = ["| " + " | ".join(head) + " |", "|---|---|---|" + "---:|" * (len(head) - 3)]
    for r in rows:
        runs = r["runs"]
        ka = r["keypoint_accuracy"]
        wrong = ka.get("wrong_track_share")
        cells = [r["scene"], r["setting"], r["side"],
                 _median_range([x["num_reg_images"] for x in runs], False) + f"/{runs[0]['num_images']}",
                 *[_median_range([x[auc_key(t)] for x in runs], True) for t in AUCS],
                 "-" if ka.get("residual_median_px") is None else f"{ka['residual_median_px']:.3f}",
                 "-" if wrong is None else f"{100 * wrong:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_known_cameras"), help="refined databases, models")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_accuracy"),
                    help="database cache (shared with bench_accuracy.py)")
    ap.add_argument("--scenes", nargs="+", default=list(SHARED_SCENES))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--repeats", type=int, default=3, help="mapping runs per side (seeds 0..N-1)")
    ap.add_argument("--recipe", default=None, help="recipe (default mop_miho_lsm)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--workers", type=int, default=1, help="refine_database workers (default 1)")
    ap.add_argument("--threads", type=int, default=1, help="mapper threads (default 1: deterministic per seed)")
    ap.add_argument("--refine-intrinsics", default="none", choices=["all", "default", "none"])
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--json", type=Path, default=None, help="write every run's row as JSON")
    ap.add_argument("--table-from", type=Path, default=None, metavar="JSON",
                    help="print the table of an earlier run's --json file and exit")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.table_from:
        print(table(json.loads(args.table_from.read_text(encoding="utf-8"))["rows"]))
        return 0

    import pycolmap

    from colmap_miho.recipe import load_recipe
    from colmap_miho.reporting.compare import gt_intrinsics
    from colmap_miho.reporting.gt_model import load_gt_poses
    from colmap_miho.reporting.report import (
        database_keypoint_accuracy,
        read_database_inliers,
    )

    pycolmap.logging.minloglevel = 1
    recipe = load_recipe(args.recipe, [*args.overrides, f"mapping.num_threads={args.threads}",
                                       f"mapping.refine_intrinsics={args.refine_intrinsics}"])
    t_all = time.perf_counter()
    rows: list[dict] = []
    for scene in args.scenes:
        root = args.data / scene
        if not (root / "images").is_dir() or not (root / "gt_model").is_dir():
            print(f"skip {scene}: no images/ or gt_model/ under {root}", file=sys.stderr)
            continue
        image_dir, gt = root / "images", root / "gt_model"
        gt_poses, intrinsics = load_gt_poses(gt), gt_intrinsics(gt)
        for setting in args.settings:
            db = build_database(image_dir, args.cache / scene, setting, args.max_features)
            work = args.work / scene / setting
            work.mkdir(parents=True, exist_ok=True)
            refined = refined_database(db, image_dir, work, recipe, args.overrides, args.workers)
            for side, database in (("baseline", db), ("colmap-miho", refined)):
                ka = database_keypoint_accuracy(read_database_inliers(database), gt_poses)
                runs = map_runs(database, image_dir, gt, work / side, args.repeats, recipe.mapping, intrinsics)
                rows.append({"scene": scene, "setting": setting, "side": side, "database": str(database),
                             "keypoint_accuracy": ka, "runs": runs})
            print(f"{scene}/{setting} done at {time.perf_counter() - t_all:.0f} s", file=sys.stderr)
            if args.json:  # partial results survive an interrupted run
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps({"argv": sys.argv[1:] if argv is None else list(argv),
                                                 "rows": rows}, indent=2), encoding="utf-8")
    wall = time.perf_counter() - t_all
    print(f"recipe {recipe.name} {' '.join('--set ' + o for o in args.overrides)}; GT intrinsics, "
          f"refine_intrinsics={args.refine_intrinsics}; median of {args.repeats} mapping runs "
          f"(seeds 0..{args.repeats - 1}, "
          f"{args.threads} thread(s)), range in brackets; model pose AUC over all GT pairs; GT residual = median "
          f"residual of the stored inliers' tracks triangulated with the GT cameras (tracks <= 4 px), wrong = "
          f"tracks > 4 px; {wall:.0f} s")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
