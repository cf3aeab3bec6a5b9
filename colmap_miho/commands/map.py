"""``colmap-miho map``: Structure-from-Motion on a COLMAP database with pycolmap."""

from __future__ import annotations

import json
from pathlib import Path

HELP = "map a COLMAP database with pycolmap (incremental or global) and write the largest model"
ORDER = 30


def add_arguments(parser) -> None:
    parser.add_argument("--database", required=True, type=Path, help="COLMAP database (read through a copy, never modified)")
    parser.add_argument("--images", required=True, type=Path, help="image folder")
    parser.add_argument("--output", required=True, type=Path, help="folder for the model (largest by registered images)")
    parser.add_argument("--mapper", default="incremental", choices=["incremental", "global"], help="pycolmap pipeline (default incremental)")
    parser.add_argument("--seed", type=int, default=0, help="mapper random seed (default 0)")
    parser.add_argument("--threads", type=int, default=-1, help="mapper threads (-1 all; 1 for bit-exact repeat runs)")
    parser.add_argument("--min-num-matches", type=int, default=15, help="ignore pairs with fewer verified inliers (default 15)")
    parser.add_argument("--json", type=Path, default=None, help="write the mapping summary as JSON")


def run(args) -> int:
    from ..sfm import require_success, run_mapping

    result = run_mapping(
        args.database, args.images, args.output, mapper=args.mapper, seed=args.seed,
        num_threads=args.threads, min_num_matches=args.min_num_matches,
        progress=not args.quiet, verbose=args.verbose,
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result.to_dict(), indent=2), encoding="utf-8")
    require_success(result)
    if not args.quiet:
        print(f"{result.num_reg_images}/{result.num_images} images registered, {result.num_points3D} points "
              f"({result.mapper}, {result.seconds:.1f} s) -> {result.output}")
    return 0
