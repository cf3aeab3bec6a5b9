"""``colmap-miho compare``: map a database as it is and after colmap-miho; tables and plots."""

from __future__ import annotations

from pathlib import Path

from ..enums import Device, Mapper

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
    """--recipe / --set / --workers / --device / --seed / --mapper, shared with run and demo
    (read them with :func:`load_run_recipe`)."""
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_ncc)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set filter.t_l=12 (repeatable)")
    parser.add_argument("--mapper", default=None, choices=Mapper.values(),
                        help="pycolmap mapper (default: the recipe's mapping.mapper, incremental)")
    parser.add_argument("--workers", type=int, default=None, help="processes filtering pairs (default: all cores)")
    parser.add_argument("--device", choices=Device.values(), default=Device.AUTO.value, help="torch device")
    parser.add_argument("--seed", type=int, default=0, help="seed of refinement, mapping and RANSAC")


def load_run_recipe(args):
    """The recipe of compare / run / demo: ``--recipe`` and ``--set``, then the flags, which
    override it (``--mapper`` -> ``mapping.mapper``, ``--seed`` -> ``mapping.seed``).

    Raises:
        ValueError: a bad recipe or value, or a ``mapping`` key that these commands do not
            apply yet (only ``map`` passes ``num_threads`` and ``min_num_matches``).
    """
    from ..recipe import load_recipe
    from ..sfm import MappingConfig

    overrides = [*args.overrides, f"mapping.seed={args.seed}"]
    if args.mapper:
        overrides.append(f"mapping.mapper={args.mapper}")
    recipe = load_recipe(args.recipe, overrides)
    for key in ("num_threads", "min_num_matches"):
        if getattr(recipe.mapping, key) != getattr(MappingConfig(), key):
            raise ValueError(f"mapping.{key} is applied by `colmap-miho map` only (compare, run "
                             "and demo map with the defaults)")
    return recipe


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

    recipe = load_run_recipe(args)
    quiet_colmap(args.verbose)
    result = compare_databases(
        args.database, args.images, args.output, gt=args.gt, pairs=args.pairs, recipe=recipe,
        mapper=recipe.mapping.mapper.value, seed=recipe.mapping.seed, workers=args.workers, device=args.device,
        progress=not args.quiet, verbose=args.verbose,
    )
    if not args.quiet:
        print(format_comparison(result))
    return 0
