"""``colmap-miho export``: write a COLMAP database's keypoints and matches as hloc h5 files
(:func:`colmap_miho.adapters.exchange.export_hloc`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

NAME = "export"
HELP = "write a database's keypoints and matches as hloc / deep-image-matching h5 files"
ORDER = 90
DESCRIPTION = (
    "Export the (refined) keypoints and (filtered) matches of a COLMAP database to an hloc "
    "features.h5 and matches.h5 (or deep-image-matching's matches layout). The database is "
    "read through a temporary copy and never modified."
)

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--database", type=Path, required=True, help="COLMAP database to read (not modified)")
    p.add_argument("--features", type=Path, required=True, help="output features.h5")
    p.add_argument("--matches", type=Path, required=True, help="output matches.h5")
    p.add_argument("--source", choices=("verified", "raw"), default="verified",
                   help="two-view-geometry inliers (verified, default) or the matches table (raw)")
    p.add_argument("--layout", choices=("hloc", "dim"), default="hloc",
                   help="matches.h5 layout: hloc's name0/name1/matches0 (default) "
                        "or deep-image-matching's (M, 2) name0/name1")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")


def paths(args: argparse.Namespace) -> tuple[dict, dict]:
    """Inputs and outputs for the CLI's overlap check."""
    return {"--database": args.database}, {"--features": args.features, "--matches": args.matches}


def run(args: argparse.Namespace) -> int:
    from ..adapters.exchange import export_hloc

    stats = export_hloc(
        args.database, args.features, args.matches, source=args.source, layout=args.layout,
        overwrite=args.overwrite, progress=not args.quiet,
    )
    log.info(
        "wrote %s (%d images, %d keypoints) and %s (%d pairs, %d matches)",
        args.features, stats.num_images, stats.num_keypoints, args.matches, stats.num_pairs, stats.num_matches,
    )
    if stats.num_dropped:
        log.warning(
            "%d matches dropped: hloc's matches0 holds one match per keypoint of the first image "
            "(use --layout dim to keep all)", stats.num_dropped,
        )
    return 0
