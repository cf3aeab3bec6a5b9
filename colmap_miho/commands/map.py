"""``colmap-miho map``: Structure-from-Motion on a COLMAP database with pycolmap."""

from __future__ import annotations

import json
from pathlib import Path

from ..enums import Mapper
from ._options import add_camera_arguments, add_refine_intrinsics_argument

HELP = "map a COLMAP database with pycolmap (incremental or global) and write the largest model"
ORDER = 30


def add_arguments(parser) -> None:
    parser.add_argument("--database", required=True, type=Path,
                        help="COLMAP database (read through a copy, never modified)")
    parser.add_argument("--images", required=True, type=Path, help="image folder")
    parser.add_argument("--output", required=True, type=Path,
                        help="folder for the model (largest by registered images)")
    parser.add_argument("--recipe", default=None,
                        help="recipe name or .toml path whose [mapping] table is used (default mop_miho_lsm)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set mapping.num_threads=1 (repeatable)")
    parser.add_argument("--mapper", default=None, choices=Mapper.values(),
                        help="pycolmap pipeline (default incremental)")
    parser.add_argument("--seed", type=int, default=0, help="the root seed; the mapper's derives from it (default 0)")
    parser.add_argument("--threads", type=int, default=None,
                        help="mapper threads (-1 all, the default; 1 for bit-exact repeat runs)")
    parser.add_argument("--min-num-matches", type=int, default=None,
                        help="ignore pairs with fewer verified inliers (default 15)")
    add_camera_arguments(parser)
    add_refine_intrinsics_argument(parser)
    parser.add_argument("--json", type=Path, default=None, help="write the mapping summary as JSON")


def paths(args) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check; a text model in --output is refused."""
    from ..adapters.paths import folder_files, model_files, refuse_folder_inside, refuse_text_model

    if args.output.exists() and not args.output.is_dir():
        raise NotADirectoryError(f"--output {args.output} is a file; give a folder for the model")
    refuse_folder_inside(args.output, "--output", args.images, "--images")
    refuse_text_model(args.output, "--output")
    return ({"--database": args.database, "--images": args.images, **folder_files(args.images, "--images")},
            {"--json": args.json, **model_files(args.output, "--output")})


def run(args) -> int:
    from ..recipe import load_recipe
    from ..seeds import mapping_seed
    from ..sfm import require_success, run_mapping
    from ._options import mapping_overrides

    config = load_recipe(args.recipe, [*args.overrides, *mapping_overrides(args)]).mapping
    result = run_mapping(args.database, args.images, args.output, config, seed=mapping_seed(args.seed),
                         progress=not args.quiet, verbose=args.verbose)
    if args.json:
        from ..adapters.staged_write import write_text_atomic

        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.json, json.dumps(result.to_dict(), indent=2))
    require_success(result)
    if not args.quiet:
        print(f"{result.num_reg_images}/{result.num_images} images registered, {result.num_points3D} points "
              f"({result.mapper}, {result.seconds:.1f} s) -> {result.output}")
    return 0
