"""``colmap-miho import``: build a NEW COLMAP database from hloc / deep-image-matching h5 files.

Keypoints in the h5 files follow hloc's convention (integer = pixel centre, as OpenCV and
kornia); COLMAP puts the image corner at (0, 0), so +0.5 is added on the way in, by the
database layer's :func:`colmap_miho.adapters.database.pixel_centre_to_colmap` (the one place of that
shift). deep-image-matching's own importer writes its keypoints without the shift;
``--keypoint-origin corner`` reproduces its databases exactly.

The database is written to ``<database>.partial`` and renamed at the end: a failed import leaves
nothing behind, and an existing database is never touched.
"""

from __future__ import annotations

import argparse
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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

@dataclass(frozen=True)
class ImportStats:
    """What an import wrote: counts of images, cameras, keypoints, pairs, matches, and (after
    verification) pairs with a two-view geometry and their inlier matches."""

    num_images: int
    num_cameras: int
    num_keypoints: int
    num_pairs: int
    num_matches: int
    num_verified_pairs: int
    num_inlier_matches: int


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--features", type=Path, required=True, help="features.h5 (hloc / deep-image-matching)")
    p.add_argument("--matches", type=Path, required=True, help="matches.h5 (hloc nested or legacy flat, or deep-image-matching)")
    p.add_argument("--pairs", type=Path, help="pairs.txt ('name0 name1' a line): import only these pairs (default: every pair in matches.h5)")
    p.add_argument("--images", type=Path, required=True, help="image folder; the h5 image names are paths relative to it")
    p.add_argument("--database", type=Path, required=True, help="the NEW database to create (must not exist)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", help="COLMAP camera model (default: %(default)s)")
    p.add_argument("--single-camera", action="store_true", help="one camera shared by all images (they must have one size)")
    p.add_argument("--verify", action=argparse.BooleanOptionalAction, default=True,
                   help="run COLMAP's geometric verification (default); --no-verify stores every match as an inlier")
    p.add_argument("--min-match-score", type=float, default=None, help="drop matches whose matching score is below this")
    p.add_argument("--keypoint-origin", choices=("center", "corner"), default="center",
                   help="h5 keypoints put pixel centres at integers (center: hloc, default) or are already in COLMAP's convention (corner)")
    p.add_argument("--seed", type=int, default=0, help="RANSAC seed of the verification (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    import pycolmap

    saved = pycolmap.logging.minloglevel
    if not args.verbose:
        pycolmap.logging.minloglevel = 1  # COLMAP's INFO lines only with -v
    try:
        stats = _run(args)
    finally:
        pycolmap.logging.minloglevel = saved
    log.info(
        "wrote %s: %d images, %d cameras, %d keypoints, %d pairs with %d matches, "
        "%d verified pairs with %d inlier matches",
        args.database, stats.num_images, stats.num_cameras, stats.num_keypoints, stats.num_pairs,
        stats.num_matches, stats.num_verified_pairs, stats.num_inlier_matches,
    )
    return 0


def _run(args: argparse.Namespace) -> ImportStats:
    return import_hloc(
        args.features, args.matches, args.images, args.database,
        pairs=args.pairs, camera_model=args.camera_model, single_camera=args.single_camera,
        verify=args.verify, min_match_score=args.min_match_score,
        keypoint_origin=args.keypoint_origin, seed=args.seed, progress=not args.quiet,
    )


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        return im.size  # (width, height)


def import_hloc(
    features: Path,
    matches: Path,
    images: Path,
    database: Path,
    *,
    pairs: Path | None = None,
    camera_model: str = "SIMPLE_RADIAL",
    single_camera: bool = False,
    verify: bool = True,
    min_match_score: float | None = None,
    keypoint_origin: str = "center",
    seed: int = 0,
    progress: bool = False,
) -> ImportStats:
    """Create ``database`` from hloc-layout h5 files, streaming one image / pair at a time.

    Keypoints are written as COLMAP's 6 columns (x, y, a11, a12, a21, a22); the affine shape is
    built from hloc's ``scales``/``oris`` when present, else identity. Raises
    ``FileExistsError`` if ``database`` exists, ``FileNotFoundError`` / ``ValueError`` naming the
    file, image or pair for malformed or mismatched inputs.
    """
    import pycolmap

    from ..adapters import hloc

    features, matches, images, database = Path(features), Path(matches), Path(images), Path(database)
    if database.exists():
        raise FileExistsError(f"{database} exists: import writes a new database only")
    if not images.is_dir():
        raise NotADirectoryError(f"{images}: image folder not found")
    if keypoint_origin not in ("center", "corner"):
        raise ValueError(f"keypoint_origin={keypoint_origin!r} is not one of: center, corner")
    pair_list = hloc.read_pairs_file(pairs) if pairs is not None else None
    partial = database.with_name(database.name + ".partial")
    _remove_db_files(partial)
    try:
        with hloc.open_h5(features) as fh, hloc.open_h5(matches) as mh:
            db = pycolmap.Database.open(str(partial))
            try:
                with pycolmap.DatabaseTransaction(db):
                    ids, nkp, ncams = _write_images(db, fh, images, camera_model, single_camera, keypoint_origin, progress)
                    npairs, nmatches = _write_matches(db, mh, ids, nkp, pair_list, verify, min_match_score, progress)
            finally:
                db.close()
        if verify:
            opts = pycolmap.TwoViewGeometryOptions()
            opts.ransac.random_seed = int(seed)
            pycolmap.geometric_verification(str(partial), two_view_geometry_options=opts)
        db = pycolmap.Database.open(str(partial))
        try:
            nver, ninl = db.num_verified_image_pairs(), db.num_inlier_matches()
        finally:
            db.close()
        os.replace(partial, database)
    except BaseException:
        _remove_db_files(partial)
        raise
    _remove_db_files(partial)  # -wal/-shm leftovers of the partial name
    return ImportStats(
        num_images=len(ids), num_cameras=ncams, num_keypoints=int(sum(nkp.values())), num_pairs=npairs,
        num_matches=nmatches, num_verified_pairs=int(nver), num_inlier_matches=int(ninl),
    )


def _remove_db_files(path: Path) -> None:
    for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm"), Path(f"{path}-journal")):
        p.unlink(missing_ok=True)


def _write_images(db, fh, images: Path, camera_model: str, single_camera: bool, keypoint_origin: str, progress: bool):
    import pycolmap
    from tqdm import tqdm

    from ..adapters import hloc
    from ..adapters.database import pixel_centre_to_colmap

    names = hloc.list_feature_images(fh)
    ids: dict[str, int] = {}
    nkp: dict[str, int] = {}
    shared: tuple[int, int, tuple[int, int], str] | None = None  # camera id, rig id, size, first image
    ncams = 0
    for name in tqdm(names, desc="images", unit="img", disable=not progress):
        path = images / name
        if not path.is_file():
            raise FileNotFoundError(f"image {name!r} of {fh.filename} is not in the image folder {images}")
        size = _image_size(path)
        if single_camera and shared is not None:
            cam_id, rig_id, first_size, first = shared
            if size != first_size:
                raise ValueError(f"--single-camera: image {name!r} is {size[0]}x{size[1]} but {first!r} is {first_size[0]}x{first_size[1]}")
        else:
            try:
                cam = pycolmap.Camera.create_from_model_name(0, camera_model, 1.2 * max(size), size[0], size[1])
            except ValueError:
                raise ValueError(f"camera_model={camera_model!r} is not a COLMAP camera model (e.g. SIMPLE_RADIAL, PINHOLE, OPENCV)") from None
            cam_id = db.write_camera(cam)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id))
            rig_id = db.write_rig(rig)
            shared = (cam_id, rig_id, size, name)
            ncams += 1
        image_id = db.write_image(pycolmap.Image(name=name, camera_id=cam_id))
        frame = pycolmap.Frame()
        frame.rig_id = rig_id
        frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id), image_id))
        db.write_frame(frame)
        feats = hloc.read_features(fh, name)
        xy = pixel_centre_to_colmap(feats.keypoints) if keypoint_origin == "center" else feats.keypoints
        rows = np.zeros((len(xy), 6), dtype=np.float32)
        rows[:, :2] = xy
        if feats.shapes is not None:
            rows[:, 2:] = feats.shapes.reshape(-1, 4)
        else:
            rows[:, 2], rows[:, 5] = 1.0, 1.0
        db.write_keypoints(image_id, rows)
        ids[name], nkp[name] = image_id, len(xy)
    return ids, nkp, ncams


def _write_matches(db, mh, ids, nkp, pair_list, verify: bool, min_match_score, progress: bool):
    import pycolmap
    from tqdm import tqdm

    from ..adapters import hloc

    npairs = nmatches = 0
    no_scores = 0
    pairs_iter = hloc.iter_matches(mh, nkp, pair_list)
    for pm in tqdm(pairs_iter, desc="pairs", unit="pair", total=len(pair_list) if pair_list else None, disable=not progress):
        m = pm.matches
        if min_match_score is not None:
            if pm.scores is None:
                no_scores += 1
            else:
                m = m[pm.scores >= min_match_score]
        m = m.astype(np.uint32)
        id0, id1 = ids[pm.name0], ids[pm.name1]
        db.write_matches(id0, id1, m)
        if not verify:
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            tvg.inlier_matches = m
            db.write_two_view_geometry(id0, id1, tvg)
        npairs += 1
        nmatches += len(m)
    if no_scores:
        log.warning("--min-match-score ignored for %d pairs without matching scores", no_scores)
    return npairs, nmatches
