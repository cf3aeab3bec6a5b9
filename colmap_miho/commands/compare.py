"""``colmap-miho compare``: map a database as it is and after colmap-miho; tables and plots."""

from __future__ import annotations

from pathlib import Path

HELP = "baseline vs colmap-miho on one database: map both, evaluate, write table + plots"
DESCRIPTION = (
    "Map the database as it is (baseline) and after `refine` (same mapper and seed), evaluate "
    "both (against --gt when given: pose AUCs, and the keypoint accuracy of each database's inlier "
    "matches under the GT geometry), and write OUTPUT/compare.md, compare.json and PNG plots "
    "(cumulative pose-error curves, keypoint displacements, matches kept per pair). The input "
    "database is never modified."
)
ORDER = 50


def add_recipe_arguments(parser) -> None:
    """--recipe / --set / --workers / --device / --seed / --mapper, shared with run and demo."""
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_ncc)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set filter.t_l=12 (repeatable)")
    parser.add_argument("--mapper", default="incremental", choices=["incremental", "global"], help="pycolmap mapper")
    parser.add_argument("--workers", type=int, default=None, help="processes filtering pairs (default: all cores)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="torch device")
    parser.add_argument("--seed", type=int, default=0, help="seed of refinement, mapping and RANSAC")


def add_arguments(parser) -> None:
    parser.add_argument("--database", required=True, type=Path, help="COLMAP database (never modified)")
    parser.add_argument("--images", required=True, type=Path, help="image folder")
    parser.add_argument("--output", required=True, type=Path, help="comparison folder")
    parser.add_argument("--gt", type=Path, default=None, help="GT COLMAP model folder (or dataset folder with gt_model/)")
    parser.add_argument("--pairs", type=Path, default=None, help="pairs file for the two-view AUCs")
    add_recipe_arguments(parser)


def quiet_colmap(verbose: bool) -> None:
    """Keep COLMAP's INFO lines off the terminal outside the mapper (which logs to a file)."""
    if not verbose:
        import pycolmap

        pycolmap.logging.minloglevel = 1


def run(args) -> int:
    from ..reporting.compare import compare_databases, format_comparison
    from ..recipe import load_recipe

    recipe = load_recipe(args.recipe, args.overrides)
    quiet_colmap(args.verbose)
    result = compare_databases(
        args.database, args.images, args.output, gt=args.gt, pairs=args.pairs, recipe=recipe,
        mapper=args.mapper, seed=args.seed, workers=args.workers, device=args.device,
        progress=not args.quiet, verbose=args.verbose,
    )
    if not args.quiet:
        print(format_comparison(result))
    return 0
