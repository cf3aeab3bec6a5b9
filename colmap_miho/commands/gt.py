"""``colmap-miho gt``: convert a benchmark's ground truth into a COLMAP model folder."""

from __future__ import annotations

import logging
from pathlib import Path

HELP = "convert benchmark ground truth (Strecha .camera, Middlebury _par.txt) to a COLMAP model"
DESCRIPTION = (
    "Write a COLMAP text model (PINHOLE cameras, GT poses, no points) that `colmap-miho report "
    "--gt` and `compare --gt` read. Strecha: --input is the folder of <image>.camera files "
    "(intrinsics are rescaled when the images are smaller than the GT, e.g. half resolution). "
    "Middlebury: --input is the *_par.txt file or its folder."
)
ORDER = 90

log = logging.getLogger(__name__)


def add_arguments(parser) -> None:
    parser.add_argument("--format", required=True, choices=["strecha", "middlebury"], help="dataset layout")
    parser.add_argument("--input", required=True, type=Path,
                        help="GT folder (strecha) or *_par.txt / its folder (middlebury)")
    parser.add_argument("--images", required=True, type=Path, help="image folder (names and sizes)")
    parser.add_argument("--output", required=True, type=Path, help="output COLMAP model folder")


def paths(args) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check (the model files written in --output)."""
    from ..adapters.paths import folder_files, model_files

    inputs = {"--input": args.input, "--images": args.images, **folder_files(args.images, "--images")}
    if args.input.is_dir():
        inputs.update(folder_files(args.input, "--input"))
    return inputs, model_files(args.output, "--output")


def run(args) -> int:
    from ..reporting.gt_model import convert_gt

    if not args.input.exists():
        raise FileNotFoundError(f"--input not found: {args.input}")
    poses = convert_gt(args.format, args.input, args.images, args.output)
    log.info("wrote %d GT poses to %s", len(poses), args.output)
    print(f"wrote {len(poses)} ground-truth poses to {args.output}")
    return 0
