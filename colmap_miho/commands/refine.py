"""``colmap-miho refine``: filter and refine the matches of a COLMAP database, safely."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..enums import Device, MatchSource
from ..errors import InvalidInput

#: ``--dask`` without a value: a local cluster (``pipeline.executor.LOCAL``; not imported
#: here, the parser is built without importing the pipeline).
DASK_LOCAL = "local"

HELP = ("filter (MOP+MiHo), check against a global camera estimate, and refine (track-consistent NCC + LSM) "
        "the matches of a COLMAP database")
DESCRIPTION = (
    "Filter every image pair of a COLMAP database with MOP+MiHo; judge every kept match against "
    "one global estimate of the cameras (the match check, on in the default recipe mop_miho_lsm: "
    "it removes the wrong matches of repeated structure that pass every per-pair filter; "
    "--set match_check.mode=off skips it); refine the kept keypoints along tracks (each keypoint "
    "moves at most once: NCC, then least-squares matching from each NCC peak); and write the "
    "result to a new database (default <stem>.miho.db beside the input; the input is never "
    "modified), or with --in-place replace the input atomically after a timestamped backup."
)
ORDER = 10

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--database", required=True, type=Path, help="input COLMAP database")
    parser.add_argument("--images", required=True, type=Path, help="image folder of the database")
    out = parser.add_mutually_exclusive_group()
    out.add_argument("--output", type=Path, help="output database (default <stem>.miho.db beside the input)")
    out.add_argument("--in-place", action="store_true",
                     help="replace the input atomically, after copying it to <name>.<time>.bak")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --output")
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_lsm)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, table.key=value, e.g. --set filter.t_l=12, --set lsm.radius=6; "
                             "tables: filter, ncc, lsm, rectify, tracks, pipeline, match_check (repeatable)")
    parser.add_argument("--source", choices=MatchSource.values(), default=None,
                        help="filter the verified inliers (two_view_geometries, default) or the "
                             "raw tentative matches (MOP+MiHo then replaces geometric verification)")
    parser.add_argument("--no-refine", action="store_true", help="filter only, no refinement (keypoints do not move)")
    parser.add_argument("--verify", action=argparse.BooleanOptionalAction, default=None,
                        help="re-run COLMAP's epipolar verification on the kept matches "
                             "(default: the recipe's pipeline.verify, off)")
    parser.add_argument("--workers", type=int, default=None,
                        help="processes filtering pairs and refining tracks, or the workers of a local "
                             "--dask cluster (default: all cores)")
    parser.add_argument("--dask", nargs="?", const=DASK_LOCAL, default=None, metavar="ADDRESS",
                        help="run the filtering and refinement on Dask: no value starts a local cluster of "
                             "--workers processes, tcp://host:8786 uses a running scheduler (its workers "
                             "must see --images at the same path and run the same colmap-miho)")
    parser.add_argument("--memory-budget", type=int, default=None, metavar="MB",
                        help="memory for the run's working data in MiB: sizes the filter's chunks of pairs "
                             "and the refinement's image cache (default: the recipe's "
                             "pipeline.memory_budget_mb); results do not depend on it")
    resume = parser.add_mutually_exclusive_group()
    resume.add_argument("--resume", action="store_true",
                        help="continue an interrupted run from its finished work (kept in "
                             ".<output name>.miho-run beside the output); same inputs and options")
    resume.add_argument("--restart", action="store_true",
                        help="discard an interrupted run's finished work and start again")
    parser.add_argument("--device", choices=Device.values(), default=Device.AUTO.value, help="torch device")
    parser.add_argument("--seed", type=int, default=0,
                        help="the run's root seed: every stage's seed derives from it (default 0)")
    parser.add_argument("--strict", action="store_true", help="a missing or unreadable image is an error")
    parser.add_argument("--json", dest="json_path", type=Path, default=None, help="write the summary as JSON")


def paths(args: argparse.Namespace) -> tuple[dict, dict]:
    """Inputs and outputs (default output included) for the CLI's overlap check."""
    from ..adapters.paths import folder_files
    from ..adapters.safety import default_output_path

    output = None if args.in_place else args.output or default_output_path(args.database)
    return ({"--database": args.database, "--images": args.images, **folder_files(args.images, "--images")},
            {"--output": output, "--json": args.json_path})


def run(args: argparse.Namespace) -> int:
    from ..pipeline.refine_job import refine_database
    from ..recipe import load_recipe

    if args.workers is not None and args.workers < 1:
        raise InvalidInput(f"--workers must be >= 1, got {args.workers}")
    overrides = list(args.overrides)
    if args.source:
        overrides.append(f"pipeline.source={args.source}")
    if args.no_refine:
        overrides.append("pipeline.refine_keypoints=false")
    if args.verify is not None:
        overrides.append(f"pipeline.verify={str(args.verify).lower()}")
    if args.memory_budget is not None:
        overrides.append(f"pipeline.memory_budget_mb={args.memory_budget}")
    recipe = load_recipe(args.recipe, overrides)
    if not args.verbose:
        import pycolmap

        pycolmap.logging.minloglevel = 2
    summary = refine_database(
        args.database, args.images, args.output, recipe=recipe, in_place=args.in_place,
        overwrite=args.overwrite, workers=args.workers, device=args.device, seed=args.seed,
        strict=args.strict, progress=not args.quiet, json_path=args.json_path, resume=args.resume,
        restart=args.restart, dask=args.dask,
    )
    if not args.quiet:
        from ..pipeline.refine_job import note_output_written
        from ..terminal import printable_fields

        try:
            print(printable_fields(summary).format())  # image names are data: no raw control characters
        except BaseException as exc:  # Ctrl-C while printing: the output is written all the same
            note_output_written(exc, summary)
            raise
    return 0
