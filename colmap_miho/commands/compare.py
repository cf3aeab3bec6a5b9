"""``colmap-miho compare``: map a database as it is and after colmap-miho; tables and plots."""

from __future__ import annotations

from pathlib import Path

from ._options import (
    add_auc_arguments,
    add_camera_arguments,
    add_recipe_arguments,
    add_repeat_arguments,
    auc_thresholds,
    check_repeat_arguments,
    load_run_recipe,
    quiet_colmap,
)

HELP = "baseline vs colmap-miho on one database: map both, evaluate, write table + plots"
DESCRIPTION = (
    "Map the database as it is (baseline) and after `refine` (same mapper and seed), evaluate "
    "both (against --gt when given: pose AUCs at --auc-thresholds, and the keypoint accuracy of "
    "each database's inlier matches under the GT geometry), and write OUTPUT/compare.md, "
    "compare.json, report.html (open it in a browser) and PNG plots (cumulative pose-error "
    "curves, keypoint displacements, matches kept per pair). Known cameras: "
    "--camera-model/--camera-params or --camera-from-gt, with --refine-intrinsics none. "
    "--repeats N maps each side N times and reports median and range. The input database is "
    "never modified."
)
ORDER = 50


def add_arguments(parser) -> None:
    parser.add_argument("--database", required=True, type=Path, help="COLMAP database (never modified)")
    parser.add_argument("--images", required=True, type=Path, help="image folder")
    parser.add_argument("--output", required=True, type=Path, help="comparison folder")
    parser.add_argument("--gt", type=Path, default=None,
                        help="GT COLMAP model folder (or dataset folder with gt_model/)")
    parser.add_argument("--pairs", type=Path, default=None, help="pairs file for the two-view AUCs")
    add_recipe_arguments(parser)
    add_camera_arguments(parser)
    add_repeat_arguments(parser)
    add_auc_arguments(parser)



def paths(args) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check; a missing --gt or a text model where mapping
    writes is refused before the long runs."""
    from ..adapters.paths import comparison_paths

    if args.gt is not None and not args.gt.exists():
        raise FileNotFoundError(f"--gt not found: {args.gt}")
    return comparison_paths(args.output, database=args.database, images=args.images, gt=args.gt,
                            pairs=args.pairs, repeats=args.repeats, seed=args.seed)


def run(args) -> int:
    from ..extras import require
    from ..pipeline.jobs import JobOptions, compare_databases
    from ..reporting.compare import format_comparison

    require("matplotlib", "plots", "compare's figures")  # before the long mapping runs
    recipe = load_run_recipe(args)
    check_repeat_arguments(args)
    thresholds = auc_thresholds(args)
    quiet_colmap(args.verbose)
    result = compare_databases(
        args.database, args.images, args.output, gt=args.gt, pairs=args.pairs, recipe=recipe,
        options=JobOptions(seed=args.seed, repeats=args.repeats, gt_cameras=args.camera_from_gt,
                           thresholds=thresholds, workers=args.workers, device=args.device,
                           progress=not args.quiet, verbose=args.verbose),
    )
    if not args.quiet:
        print(format_comparison(result))
    return 0
