"""``colmap-miho export``: write a COLMAP database's keypoints and matches as hloc h5 files.

The database is never opened itself: a temporary copy is read (pycolmap migrates the schema of
whatever it opens). Keypoints leave in hloc's convention (integer = pixel centre), converted by
the database layer; matches come from the two-view-geometry inliers (``--source verified``,
default: what the mapper uses, i.e. the filtered matches after ``refine``) or the raw matches
table (``--source raw``).
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
from dataclasses import dataclass
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


@dataclass(frozen=True)
class ExportStats:
    """What an export wrote. ``num_dropped``: matches that hloc's one-match-per-keypoint
    ``matches0`` could not hold (0 with ``layout='dim'``)."""

    num_images: int
    num_keypoints: int
    num_pairs: int
    num_matches: int
    num_dropped: int


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--database", type=Path, required=True, help="COLMAP database to read (not modified)")
    p.add_argument("--features", type=Path, required=True, help="output features.h5")
    p.add_argument("--matches", type=Path, required=True, help="output matches.h5")
    p.add_argument("--source", choices=("verified", "raw"), default="verified",
                   help="two-view-geometry inliers (verified, default) or the matches table (raw)")
    p.add_argument("--layout", choices=("hloc", "dim"), default="hloc",
                   help="matches.h5 layout: hloc's name0/name1/matches0 (default) or deep-image-matching's (M, 2) name0/name1")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")


def run(args: argparse.Namespace) -> int:
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


def export_hloc(
    database: Path,
    features: Path,
    matches: Path,
    *,
    source: str = "verified",
    layout: str = "hloc",
    overwrite: bool = False,
    progress: bool = False,
) -> ExportStats:
    """Write ``features`` (per image ``keypoints`` (N, 2) float32, integer = pixel centre, and
    ``image_size`` (width, height)) and ``matches`` (one group per pair with matches, image order
    of the database pair: smaller image id first) from ``database``.

    Both files are written under temporary names and renamed at the end. Raises
    ``FileExistsError`` for an existing output without ``overwrite``, ``DatabaseError`` for a
    missing, locked or non-COLMAP database.
    """
    from tqdm import tqdm

    from ..enums import MatchSource
    from ..adapters import hloc
    from ..adapters.database import ColmapDatabase, validate_database
    from ..adapters.safety import check_database_path, check_not_in_use, copy_file

    database, features, matches = Path(database), Path(features), Path(matches)
    source = MatchSource.parse(source, "source")
    if layout not in ("hloc", "dim"):
        raise ValueError(f"layout={layout!r} is not one of: hloc, dim")
    for out in (features, matches):
        if out.exists() and not overwrite:
            raise FileExistsError(f"{out} exists; pass --overwrite to replace it")
        if not out.parent.is_dir():
            raise NotADirectoryError(f"output folder does not exist: {out.parent}")
    if features.resolve() == matches.resolve():
        raise ValueError("--features and --matches must be different files")
    check_database_path(database)
    check_not_in_use(database)

    tmp_feat = features.with_name(f".{features.name}.partial")
    tmp_match = matches.with_name(f".{matches.name}.partial")
    nkp_total = npairs = nmatches = ndropped = 0
    try:
        with tempfile.TemporaryDirectory(prefix="colmap-miho-export-") as tmp:
            copy = Path(tmp) / "database.db"
            copy_file(database, copy)
            validate_database(copy)
            with ColmapDatabase(copy) as db, hloc.open_h5(tmp_feat, "w") as fh, hloc.open_h5(tmp_match, "w") as mh:
                records = db.images()
                names = {r.image_id: r.name for r in records}
                nkp: dict[int, int] = {}
                for r in tqdm(records, desc="keypoints", unit="img", disable=not progress):
                    xy = db.keypoints(r.image_id)
                    hloc.write_features(fh, r.name, xy, image_size=(r.width, r.height))
                    nkp[r.image_id] = len(xy)
                    nkp_total += len(xy)
                for pr in tqdm(db.pairs(source), desc="pairs", unit="pair", disable=not progress):
                    m = db.matches(pr.image_id1, pr.image_id2, source)
                    pm = hloc.PairMatches(names[pr.image_id1], names[pr.image_id2], m.astype("int64"))
                    ndropped += hloc.write_pair_matches(mh, pm, nkp[pr.image_id1], layout=layout)
                    npairs += 1
                    nmatches += len(m)
        os.replace(tmp_feat, features)
        os.replace(tmp_match, matches)
    finally:
        tmp_feat.unlink(missing_ok=True)
        tmp_match.unlink(missing_ok=True)
    return ExportStats(num_images=len(nkp), num_keypoints=nkp_total, num_pairs=npairs,
                       num_matches=nmatches - ndropped, num_dropped=ndropped)
