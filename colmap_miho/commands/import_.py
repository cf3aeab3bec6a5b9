"""``colmap-miho import``: build a NEW COLMAP database from hloc / deep-image-matching h5 files
(:func:`colmap_miho.adapters.exchange.import_hloc`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

NAME = "import"
HELP = "build a new COLMAP database from hloc / deep-image-matching features.h5 and matches.h5"
ORDER = 5
DESCRIPTION = (
    "Create a new COLMAP database from an hloc (or deep-image-matching) features.h5 and "
    "matches.h5: cameras from the image files (focal prior 1.2 * max(width, height)), keypoints "
    "(+0.5 to COLMAP's pixel convention), matches, and two-view geometries (verified by COLMAP "
    "unless --no-verify)."
)

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--features", type=Path, required=True, help="features.h5 (hloc / deep-image-matching)")
    p.add_argument("--matches", type=Path, required=True,
                   help="matches.h5 (hloc nested or legacy flat, or deep-image-matching)")
    p.add_argument("--pairs", type=Path,
                   help="pairs.txt ('name0 name1' a line): import only these pairs (default: every pair in matches.h5)")
    p.add_argument("--images", type=Path, required=True,
                   help="image folder; the h5 image names are paths relative to it")
    p.add_argument("--database", type=Path, required=True, help="the NEW database to create (must not exist)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model (default: %(default)s)")
    p.add_argument("--single-camera", action="store_true",
                   help="one camera shared by all images (they must have one size)")
    p.add_argument("--verify", action=argparse.BooleanOptionalAction, default=True,
                   help="run COLMAP's geometric verification (default); --no-verify stores every match as an inlier")
    p.add_argument("--min-match-score", type=float, default=None,
                   help="drop matches whose matching score is below this")
    p.add_argument("--keypoint-origin", choices=("center", "corner"), default="center",
                   help="h5 keypoints put pixel centres at integers (center: hloc, default) "
                        "or are already in COLMAP's convention (corner)")
    p.add_argument("--seed", type=int, default=0, help="RANSAC seed of the verification (default: %(default)s)")


def paths(args: argparse.Namespace) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check; the new database's folder must exist."""
    from ..adapters.paths import folder_files

    if not args.database.parent.is_dir():
        raise NotADirectoryError(f"--database folder does not exist: {args.database.parent} (create it first)")
    return ({"--features": args.features, "--matches": args.matches, "--pairs": args.pairs,
             "--images": args.images, **folder_files(args.images, "--images")}, {"--database": args.database})


def run(args: argparse.Namespace) -> int:
    import pycolmap

    from ..adapters.exchange import import_hloc

    saved = pycolmap.logging.minloglevel
    if not args.verbose:
        pycolmap.logging.minloglevel = 1  # COLMAP's INFO lines only with -v
    try:
        stats = import_hloc(
            args.features, args.matches, args.images, args.database,
            pairs=args.pairs, camera_model=args.camera_model, single_camera=args.single_camera,
            verify=args.verify, min_match_score=args.min_match_score,
            keypoint_origin=args.keypoint_origin, seed=args.seed, progress=not args.quiet,
        )
    finally:
        pycolmap.logging.minloglevel = saved
    log.info(
        "wrote %s: %d images, %d cameras, %d keypoints, %d pairs with %d matches, "
        "%d verified pairs with %d inlier matches",
        args.database, stats.num_images, stats.num_cameras, stats.num_keypoints, stats.num_pairs,
        stats.num_matches, stats.num_verified_pairs, stats.num_inlier_matches,
    )
    return 0

