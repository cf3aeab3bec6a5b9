"""hloc / deep-image-matching h5 files in and out of COLMAP databases (h5 side :mod:`.hloc`,
database side :mod:`.database`); ``keypoint_origin="corner"`` reproduces deep-image-matching's
databases."""

from __future__ import annotations

import logging
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..enums import MatchSource
from ..errors import InvalidInput
from . import hloc
from .database import ColmapDatabase, validate_database, verify_geometry
from .images import image_size
from .paths import leaves_folder
from .safety import check_database_path, check_free_space, check_integrity, check_not_in_use, read_copy
from .staged_write import disk_full_error, is_disk_full, private_tempdir, staged_write
from .working_copy import publish_new_file

log = logging.getLogger(__name__)

KEYPOINT_ORIGINS = ("center", "corner")
EXPORT_LAYOUTS = ("hloc", "dim")
FOCAL_PRIOR = 1.2
"""Focal length prior of imported cameras, times max(width, height) (COLMAP's default)."""


@dataclass(frozen=True)
class ImportStats:
    """What an import wrote: images, cameras, keypoints, pairs, matches and verified pairs and inliers."""

    num_images: int
    num_cameras: int
    num_keypoints: int
    num_pairs: int
    num_matches: int
    num_verified_pairs: int
    num_inlier_matches: int


@dataclass(frozen=True)
class ExportStats:
    """What an export wrote; ``num_dropped``: matches hloc's ``matches0`` could not hold."""

    num_images: int
    num_keypoints: int
    num_pairs: int
    num_matches: int
    num_dropped: int


def import_hloc(
    features: str | Path,
    matches: str | Path,
    images: str | Path,
    database: str | Path,
    *,
    pairs: str | Path | None = None,
    camera_model: str = "SIMPLE_RADIAL",
    single_camera: bool = False,
    verify: bool = True,
    min_match_score: float | None = None,
    keypoint_origin: str = "center",
    seed: int = 0,
    progress: bool = False,
) -> ImportStats:
    """Create the NEW ``database`` from hloc-layout h5 files, one image / pair at a time, written
    beside and moved in at the end (a failed import leaves nothing). ``verify=False`` stores every
    match as an UNCALIBRATED inlier. FileExistsError, or FileNotFoundError / ValueError naming the
    input."""
    features, matches, images, database = Path(features), Path(matches), Path(images), Path(database)
    if database.exists():
        raise FileExistsError(f"{database} exists: import writes a new database only")
    if database.is_symlink():  # a dangling link: exists() said no, the final link would say "created meanwhile"
        raise FileExistsError(f"{database} is a symlink to {os.readlink(database)}, which does not exist: import "
                              "writes a new database only, never through a link; remove the link or choose another "
                              "--database")
    if not images.is_dir():
        raise NotADirectoryError(f"{images}: image folder not found")
    if keypoint_origin not in KEYPOINT_ORIGINS:
        raise InvalidInput(f"keypoint_origin={keypoint_origin!r} is not one of: {', '.join(KEYPOINT_ORIGINS)}")
    pair_list = hloc.read_pairs_file(pairs) if pairs is not None else None
    try:
        # a private folder beside the new database (removed by the next run after a kill -9);
        # the finished database is linked onto its name only if none appeared meanwhile
        with private_tempdir(f".{database.name}.", database.parent) as tmp:
            partial = tmp / "database.db"
            with hloc.open_h5(features) as fh, hloc.open_h5(matches) as mh:
                check_import_space(fh, mh, database.parent, verify)
                with ColmapDatabase.create(partial) as db, db.transaction():
                    ids, nkp, ncams = _write_images(db, fh, images, camera_model, single_camera,
                                                    keypoint_origin == "corner", progress)
                    npairs, nmatches = _write_matches(db, mh, ids, nkp, pair_list, verify, min_match_score,
                                                      progress)
            if verify:
                verify_geometry(partial, seed=seed)
            with ColmapDatabase(partial) as db:
                nver, ninl = db.num_verified_pairs(), db.num_inlier_matches()
            check_integrity(partial, database)
            # import has no --overwrite: it only ever writes a new database
            publish_new_file(partial, database, advice="remove that file or choose another --database")
    except (OSError, RuntimeError, sqlite3.Error) as exc:
        if not is_disk_full(exc):
            raise
        raise disk_full_error(database.parent, f"importing into {database}", exc) from None
    return ImportStats(
        num_images=len(ids), num_cameras=ncams, num_keypoints=int(sum(nkp.values())), num_pairs=npairs,
        num_matches=nmatches, num_verified_pairs=nver, num_inlier_matches=ninl,
    )


def _write_images(db: ColmapDatabase, fh, images: Path, camera_model: str, single_camera: bool,
                  colmap_coordinates: bool, progress: bool) -> tuple[dict[str, int], dict[str, int], int]:
    from tqdm import tqdm

    ids: dict[str, int] = {}
    nkp: dict[str, int] = {}
    shared: tuple[int, int, tuple[int, int], str] | None = None  # camera id, rig id, size, first image
    ncams = 0
    for name in tqdm(hloc.list_feature_images(fh), desc="images", unit="img", disable=not progress):
        if leaves_folder(name):
            raise InvalidInput(f"image {name!r} of {fh.filename} is named outside the image folder {images} "
                             "(an absolute name or one with '..')")
        path = images / name
        if not path.is_file():
            raise FileNotFoundError(f"image {name!r} of {fh.filename} is not in the image folder {images}")
        size = image_size(path)
        if single_camera and shared is not None:
            cam_id, rig_id, first_size, first = shared
            if size != first_size:
                raise InvalidInput(f"--single-camera: image {name!r} is {size[0]}x{size[1]} "
                                 f"but {first!r} is {first_size[0]}x{first_size[1]}")
        else:
            cam_id, rig_id = db.add_camera(camera_model, size[0], size[1], FOCAL_PRIOR * max(size))
            shared = (cam_id, rig_id, size, name)
            ncams += 1
        image_id = db.add_image(name, cam_id, rig_id)
        feats = hloc.read_features(fh, name, image_size=size, origin=0.0 if colmap_coordinates else -0.5)
        db.add_keypoints(image_id, feats.keypoints, feats.shapes, colmap_coordinates=colmap_coordinates)
        ids[name], nkp[name] = image_id, len(feats.keypoints)
    return ids, nkp, ncams


def _write_matches(db: ColmapDatabase, mh, ids: dict[str, int], nkp: dict[str, int], pair_list,
                   verify: bool, min_match_score: float | None, progress: bool) -> tuple[int, int]:
    """The matches of every pair (of ``pair_list`` when given); returns (pairs, matches)."""
    from tqdm import tqdm

    npairs = nmatches = no_scores = 0
    pairs_iter = hloc.iter_matches(mh, nkp, pair_list)
    for pm in tqdm(pairs_iter, desc="pairs", unit="pair", total=len(pair_list) if pair_list else None,
                   disable=not progress):
        m = pm.matches
        if min_match_score is not None:
            if pm.scores is None:
                no_scores += 1
            else:
                m = m[pm.scores >= min_match_score]
        db.add_matches(ids[pm.name0], ids[pm.name1], m, as_inliers=not verify)
        npairs += 1
        nmatches += len(m)
    if no_scores:
        log.warning("--min-match-score ignored for %d pairs without matching scores", no_scores)
    if npairs == 0:
        log.warning("%s holds no pairs: the new database has no matches (is it the matches file?)", mh.filename)
    return npairs, nmatches


def export_hloc(
    database: str | Path,
    features: str | Path,
    matches: str | Path,
    *,
    source: MatchSource | str = "verified",
    layout: str = "hloc",
    overwrite: bool = False,
    progress: bool = False,
) -> ExportStats:
    """Write ``features`` and ``matches`` h5 files from a copy of ``database`` (``layout`` "hloc":
    one match per keypoint of image 0, or "dim": lossless). FileExistsError without ``overwrite``.
    """
    from tqdm import tqdm

    database, features, matches = Path(database), Path(features), Path(matches)
    source = MatchSource.parse(source, "source")
    if layout not in EXPORT_LAYOUTS:
        raise InvalidInput(f"layout={layout!r} is not one of: {', '.join(EXPORT_LAYOUTS)}")
    for out in (features, matches):
        if out.exists() and not overwrite:
            raise FileExistsError(f"{out} exists; pass --overwrite (overwrite=True in Python) to replace it")
        if not out.parent.is_dir():
            raise NotADirectoryError(f"output folder does not exist: {out.parent}")
    if features.resolve() == matches.resolve():
        raise InvalidInput("--features and --matches must be different files")
    check_database_path(database)
    check_not_in_use(database)  # before the outputs' temporary files are created

    nkp_total = npairs = nmatches = ndropped = 0
    try:
        with private_tempdir("colmap-miho-export-") as tmp:  # removed by the next run after a kill -9
            copy = Path(tmp) / "database.db"
            read_copy(database, copy)
            validate_database(copy, name=database)
            check_export_space(copy, features, matches, source, layout)
            # each file staged under a unique name beside its target, renamed when both are whole
            with staged_write(features) as tmp_feat, staged_write(matches) as tmp_match:
                with ColmapDatabase(copy) as db, hloc.open_h5(tmp_feat, "w") as fh, \
                        hloc.open_h5(tmp_match, "w") as mh:
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
                        pm = hloc.PairMatches(names[pr.image_id1], names[pr.image_id2], m.astype(np.int64))
                        ndropped += hloc.write_pair_matches(mh, pm, nkp[pr.image_id1], layout=layout)
                        npairs += 1
                        nmatches += len(m)
    except (OSError, RuntimeError) as exc:
        if not is_disk_full(exc):
            raise
        raise disk_full_error(features.parent, f"exporting {database}", exc) from None
    return ExportStats(num_images=len(nkp), num_keypoints=nkp_total, num_pairs=npairs,
                       num_matches=nmatches - ndropped, num_dropped=ndropped)


#: Bytes per stored value and per HDF5 object, with a margin (measured on hloc-layout exports
#: with h5py's default settings; an estimate for the free-space check only).
H5_BYTES_PER_GROUP = 4096
H5_MARGIN = 1.5


def check_export_space(copy: Path, features: Path, matches: Path, source: MatchSource, layout: str) -> None:
    """Refuse an export that would fill the disk (HDF5 may crash the process on a failed write)."""
    table = "two_view_geometries" if source == MatchSource.VERIFIED else "matches"
    con = sqlite3.connect(f"file:{copy.resolve()}?mode=ro", uri=True)
    try:
        images, keypoints = con.execute("SELECT COUNT(*), COALESCE(SUM(rows), 0) FROM keypoints").fetchone()
        pairs, rows = con.execute(f"SELECT COUNT(*), COALESCE(SUM(rows), 0) FROM {table} WHERE rows > 0").fetchone()
    finally:
        con.close()
    feat = keypoints * 8 + images * H5_BYTES_PER_GROUP
    # hloc: matches0 int32 + scores float32 per keypoint of image 0 (at most all its keypoints)
    per_pair = (keypoints / max(images, 1)) * 8 if layout == "hloc" else 0.0
    match = pairs * (per_pair + 2 * H5_BYTES_PER_GROUP) + (rows * 16 if layout == "dim" else 0)
    need = {features.parent: feat * H5_MARGIN, matches.parent: match * H5_MARGIN}
    if features.parent.resolve() == matches.parent.resolve():
        need = {features.parent: (feat + match) * H5_MARGIN}
    for folder, size in need.items():
        check_free_space(folder, int(size) + (1 << 20), "the exported h5 files")


#: Bytes the new database takes per keypoint (6 float32 columns) and per match (uint32 pair in
#: the matches table and again in the two-view geometries), and the headroom over that for
#: SQLite's write-ahead log and page slack (the peak use of imports measured on a tmpfs stays
#: well inside it).
DB_BYTES_PER_KEYPOINT = 24
DB_BYTES_PER_MATCH = 16
DB_WRITE_FACTOR = 2


def check_import_space(fh, mh, folder: Path, verify: bool) -> None:
    """Refuse an import that would fill the disk (pycolmap aborts on some failed writes), sized from
    the h5 shapes alone."""
    keypoints = hloc.count_rows(fh, "keypoints")
    matches = hloc.count_matches(mh)
    need = DB_WRITE_FACTOR * (keypoints * DB_BYTES_PER_KEYPOINT + matches * DB_BYTES_PER_MATCH)
    check_free_space(folder, need + (4 << 20), "the new database")
