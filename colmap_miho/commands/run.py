"""``colmap-miho run``: the whole job from a folder of images (batch entry point)."""

from __future__ import annotations

from pathlib import Path

from ..enums import CameraMode
from ._options import ListAction, add_auc_arguments, add_recipe_arguments, add_repeat_arguments

HELP = "from a folder of images: SIFT + exhaustive matching, refine, map, report (--compare: vs baseline)"
DESCRIPTION = (
    "Extract SIFT features and match them exhaustively with pycolmap (CPU) into "
    "OUTPUT/database.db (reused when it exists), then refine, map and report; with --compare the "
    "unrefined database is mapped too and the two are compared. Exit code 0 on success, 1 when "
    "mapping fails, 2 on bad input."
)
ORDER = 60


def add_arguments(parser) -> None:
    parser.add_argument("--images", required=True, type=Path, help="image folder")
    parser.add_argument("--output", required=True, type=Path, help="work folder")
    parser.add_argument("--gt", type=Path, default=None,
                        help="GT COLMAP model folder (or dataset folder with gt_model/)")
    parser.add_argument("--compare", action="store_true", help="also map the unrefined database and compare")
    parser.add_argument("--camera-mode", default=CameraMode.SINGLE.value, choices=CameraMode.values(),
                        help="COLMAP camera sharing (default: one camera for all images)")
    parser.add_argument("--camera-model", dest="extract_camera_model", default="SIMPLE_RADIAL",
                        help="COLMAP camera model (default SIMPLE_RADIAL)")
    parser.add_argument("--camera-params", dest="extract_camera_params", default="", action=ListAction, join=True,
                        metavar="P",
                        help="known intrinsics for --camera-model, COLMAP's list with commas or spaces "
                             "(e.g. PINHOLE 'fx,fy,cx,cy' or fx fy cx cy, COLMAP pixel convention), written into the "
                             "database and into the mapped copies; --refine-intrinsics none keeps them; "
                             "default: estimated")
    parser.add_argument("--max-features", type=int, default=8192, help="SIFT features per image (default 8192)")
    add_recipe_arguments(parser)
    add_repeat_arguments(parser)
    add_auc_arguments(parser)


def paths(args) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check; a missing --gt or a text model where mapping
    writes is refused before the long runs."""
    from ..adapters.paths import comparison_paths

    if args.gt is not None and not args.gt.exists():
        raise FileNotFoundError(f"--gt not found: {args.gt}")
    return comparison_paths(args.output, images=args.images, gt=args.gt, repeats=args.repeats, seed=args.seed,
                            compare=args.compare)


def run(args) -> int:
    from ..errors import UserError
    from ..extras import require
    from ..pipeline.jobs import ExtractionOptions, JobOptions, run_from_images
    from ..reporting.compare import format_comparison
    from ..reporting.report_text import format_report
    from ._options import (
        auc_thresholds,
        check_repeat_arguments,
        load_run_recipe,
        quiet_colmap,
    )

    if args.compare:
        require("matplotlib", "plots", "--compare's figures")  # before the long mapping runs
    if args.extract_camera_params:
        # known intrinsics: also written into the mapped copies (a reused database gets them there too)
        args.camera_model, args.camera_params = args.extract_camera_model, args.extract_camera_params
    recipe = load_run_recipe(args)
    check_repeat_arguments(args)
    if args.repeats > 1 and not args.compare:
        raise UserError("--repeats needs --compare (it maps both sides N times)")
    thresholds = auc_thresholds(args)
    quiet_colmap(args.verbose)
    out = run_from_images(
        args.images, args.output, gt=args.gt, recipe=recipe, compare=args.compare,
        extraction=ExtractionOptions(camera_mode=args.camera_mode, camera_model=args.extract_camera_model,
                                     camera_params=args.extract_camera_params, max_features=args.max_features),
        options=JobOptions(seed=args.seed, repeats=args.repeats, gt_cameras=args.camera_from_gt,
                           thresholds=thresholds, workers=args.workers, device=args.device,
                           progress=not args.quiet, verbose=args.verbose),
    )
    if not args.quiet:
        if args.compare:
            print(format_comparison(out["result"]))
        else:
            print(format_report(out["report_dict"]))
            print(f"\nreport: {out['report']}\nmodel:  {args.output / 'refined' / 'model'}")
    return 0
