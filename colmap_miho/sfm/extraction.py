"""COLMAP's SIFT extraction and exhaustive matching (pycolmap, CPU) into a new database, with its
free space checked first (pycolmap aborts on a full disk)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ..adapters.images import folder_image_sizes
from ..enums import CameraMode
from ..errors import InvalidInput, RunFailed
from .colmap_log import colmap_log_to_file

log = logging.getLogger(__name__)


def _names_need_escaping(image_dir: Path) -> bool:
    import os

    from ..terminal import printable

    for _root, dirs, files in os.walk(image_dir):
        if any(printable(n) != n for n in (*dirs, *files)):
            return True
    return False


def extract_and_match(
    image_dir: str | Path,
    database: str | Path,
    *,
    camera_mode: CameraMode | str = CameraMode.SINGLE,
    camera_model: str = "SIMPLE_RADIAL",
    camera_params: str = "",
    max_features: int = 8192,
    num_threads: int = -1,
    verbose: bool = False,
    log_dir: str | Path | None = None,
) -> dict:
    """COLMAP SIFT extraction and exhaustive matching (CPU) of every image in ``image_dir`` into the
    new ``database``.

    ``camera_mode``: "single", "per_image", "per_folder" or "auto"; ``camera_params``: COLMAP's
    comma-separated parameters ("" = estimate); ``num_threads`` -1 = all; without ``verbose``
    COLMAP's log goes to ``log_dir``. Returns ``{"num_images", "seconds_extract",
    "seconds_match"}``."""
    import pycolmap

    from ..arguments import check_integer, check_paths
    from ..validation import OPTION_BOUNDS, bounds_of
    from .mapping import MappingConfig, parse_camera_params

    check_paths(image_dir=image_dir, database=database, log_dir=log_dir, optional=("log_dir",))
    check_integer("max_features", max_features, OPTION_BOUNDS["max_features"])
    check_integer("num_threads", num_threads, bounds_of(MappingConfig)["num_threads"])

    parse_camera_params(str(camera_model), str(camera_params))  # COLMAP's own check says only "Check failed"
    camera_model = str(camera_model).upper()
    database = Path(database)
    if database.exists():
        raise FileExistsError(f"database already exists: {database}")
    camera_mode = CameraMode.parse(camera_mode, "camera_mode")
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise NotADirectoryError(f"image folder not found: {image_dir}")
    found = folder_image_sizes(image_dir)
    check_camera_sizes(found, camera_mode, image_dir)
    database.parent.mkdir(parents=True, exist_ok=True)
    check_extraction_space(image_dir, database.parent, max_features)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    reader.camera_params = camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = int(max_features)
    extraction.num_threads = int(num_threads)
    mode = getattr(pycolmap.CameraMode, camera_mode.name)
    # COLMAP prints each file's name raw: with a name that needs escaping, -v shows the log
    # escaped once the call ends instead of live
    with colmap_log_to_file(Path(log_dir) if log_dir else database.parent, verbose=verbose,
                            replay=verbose and _names_need_escaping(image_dir), hide=()):
        t0 = time.perf_counter()
        pycolmap.extract_features(str(database), str(image_dir), camera_mode=mode, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        t1 = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = int(num_threads)
        pycolmap.match_exhaustive(str(database), matching_options=matching, device=pycolmap.Device.cpu)
        t2 = time.perf_counter()
    if not database.is_file():
        raise RunFailed(f"feature extraction wrote no database (no readable image in {image_dir}?)")
    from ..adapters.database import ColmapDatabase

    with ColmapDatabase(database) as db:
        extracted = {im.name for im in db.images()}
    n = len(extracted)
    skipped = sorted(set(found) - extracted)
    if skipped:
        log.warning("%d of the %d images in %s were not extracted (COLMAP could not use them; its log: %s): %s",
                    len(skipped), len(found), image_dir, "the terminal" if verbose else
                    Path(log_dir) if log_dir else database.parent, _some(skipped))
    if n < 2:
        raise RunFailed(f"feature extraction found {n} image(s) in {image_dir}; need at least 2")
    log.info("extracted %d images in %.1f s, matched exhaustively in %.1f s", n, t1 - t0, t2 - t1)
    return {"num_images": n, "images_found": len(found), "images_not_extracted": skipped,
            "seconds_extract": t1 - t0, "seconds_match": t2 - t1}


def _some(names: list[str], most: int = 5) -> str:
    from ..terminal import printable

    shown = ", ".join(printable(n) for n in names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


def check_camera_sizes(sizes: dict[str, tuple[int, int]], camera_mode: CameraMode, image_dir: Path) -> None:
    """Refuse a camera mode that shares one camera between images of different sizes (COLMAP would
    silently drop the others); InvalidInput naming the sizes and the modes that fit."""
    if camera_mode not in (CameraMode.SINGLE, CameraMode.PER_FOLDER):
        return
    groups: dict[str, dict[tuple[int, int], list[str]]] = {}
    for name, size in sizes.items():
        folder = name.rpartition("/")[0] if camera_mode == CameraMode.PER_FOLDER else ""
        groups.setdefault(folder, {}).setdefault(size, []).append(name)
    for folder, by_size in groups.items():
        if len(by_size) < 2:
            continue
        ranked = sorted(by_size.items(), key=lambda kv: (-len(kv[1]), kv[0]))
        where = f"{image_dir / folder}" if folder else f"{image_dir}"
        listed = "; ".join(f"{w}x{h}: {len(names)} image(s), e.g. {_some(names, 3)}" for (w, h), names in ranked)
        fits = "per_image or auto" if camera_mode == CameraMode.PER_FOLDER else "per_folder, per_image or auto"
        raise InvalidInput(
            f"the images in {where} have {len(by_size)} sizes ({listed}); camera mode {camera_mode.value} "
            f"gives them one camera, and COLMAP would drop every image of another size: resize them, or "
            f"choose --camera-mode {fits}")


#: Bytes a new database takes per extracted feature (6 float32 keypoint columns and a 128-byte
#: SIFT descriptor), the fraction of features assumed matched per pair (two uint32 per match,
#: in the matches and again in the two-view geometries) and the headroom for SQLite's
#: write-ahead log: an estimate for the free-space check, pycolmap aborts on a full disk.
FEATURE_BYTES = 24 + 128


MATCHED_FRACTION = 0.25


EXTRACTION_WRITE_FACTOR = 2


def check_extraction_space(image_dir: Path, folder: Path, max_features: int) -> None:
    """Refuse an extraction whose database would not fit ``folder``'s free space (UserError)."""
    from ..adapters.safety import check_free_space

    n = sum(1 for p in Path(image_dir).rglob("*") if p.is_file())
    pairs = n * (n - 1) // 2
    need = EXTRACTION_WRITE_FACTOR * (n * max_features * FEATURE_BYTES
                                      + pairs * max_features * MATCHED_FRACTION * 16)
    check_free_space(folder, int(need) + (4 << 20), f"extracting and matching {n} images")
