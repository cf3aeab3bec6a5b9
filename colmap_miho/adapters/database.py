"""The only module that creates, reads and writes COLMAP databases (through pycolmap), and the one
place of the half-pixel shift (:mod:`.conventions`). Open only a working copy: pycolmap migrates the
schema on open."""

from __future__ import annotations

import contextlib
import functools
import logging
import sqlite3
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..enums import MatchSource
from ..errors import DatabaseError, InvalidInput
from ..geometry import fit_model_lsq
from ..types import Pair
from .cameras import CameraIntrinsics, camera_from
from .conventions import colmap_to_pixel_centre, image_pair, pixel_centre_to_colmap
from .database_build import DatabaseBuilder
from .safety import check_database_path

log = logging.getLogger(__name__)

REQUIRED_TABLES = ("cameras", "images", "keypoints", "matches", "two_view_geometries")


def validate_database(path: str | Path, name: str | Path | None = None) -> None:
    """Check that ``path`` is a COLMAP database (SQLite with COLMAP's tables), read-only with
    sqlite3 and no pycolmap handle open; DatabaseError names ``name`` and any missing tables."""
    p = check_database_path(path)
    shown = Path(name) if name is not None else p  # the user's file, never a hidden copy
    try:
        con = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
        try:
            rows = con.execute("SELECT name FROM sqlite_master WHERE type='table'").fetchall()
        finally:
            con.close()
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"not a COLMAP database ({exc}): {shown}") from None
    tables = {r[0] for r in rows}
    missing = [t for t in REQUIRED_TABLES if t not in tables]
    if missing:
        raise DatabaseError(f"not a COLMAP database (missing tables: {', '.join(missing)}): {shown}")
    _check_blob_sizes(p, shown)
    _check_camera_rows(p, shown)
    _check_camera_models(p, shown)
    if {"frames", "frame_data", "rigs"} <= tables:  # older schemas have none: pycolmap adds them
        _check_frames(p, shown)


def _check_camera_rows(p: Path, name: Path) -> None:
    """Refuse images whose ``camera_id`` has no camera row (the mapper would fail on it); raises
    :class:`DatabaseError` naming the file and the camera ids."""
    con = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT camera_id, name FROM images WHERE camera_id NOT IN "
                           "(SELECT camera_id FROM cameras) ORDER BY camera_id, image_id").fetchall()
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"not a COLMAP database ({exc}): {name}") from None
    finally:
        con.close()
    if not rows:
        return
    by_camera: dict[int, list[str]] = {}
    for camera_id, image in rows:
        by_camera.setdefault(int(camera_id), []).append(str(image))
    parts = []
    for camera_id, images in list(by_camera.items())[:3]:
        shown = ", ".join(repr(n) for n in images[:3]) + (f" and {len(images) - 3} more" if len(images) > 3 else "")
        parts.append(f"camera {camera_id} (used by {len(images)} image(s): {shown})")
    more = f" and {len(by_camera) - 3} more camera(s)" if len(by_camera) > 3 else ""
    raise DatabaseError(f"database {name} is damaged: the cameras table has no row for {'; '.join(parts)}{more}; "
                        "add the camera rows (or import the images again)")


def _camera_model_params() -> dict[int, tuple[str, int]]:
    """COLMAP's camera model ids -> (name, number of parameters), from pycolmap."""
    import pycolmap

    out = {}
    for name, model_id in pycolmap.CameraModelId.__members__.items():
        if int(model_id) >= 0:
            out[int(model_id)] = (name, len(pycolmap.Camera.create_from_model_id(1, model_id, 1.0, 1, 1).params))
    return out


def _check_camera_models(p: Path, name: Path) -> None:
    """Refuse a camera with an unknown model id or a parameter blob of the wrong size; raises :class:`DatabaseError`."""
    models = _camera_model_params()
    con = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT camera_id, model, length(params) FROM cameras ORDER BY camera_id").fetchall()
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"not a COLMAP database ({exc}): {name}") from None
    finally:
        con.close()
    for camera_id, model, nbytes in rows:
        if not isinstance(model, int) or model not in models:
            raise DatabaseError(f"database {name} is damaged: camera {camera_id} has model id {model!r}, which is "
                                f"no COLMAP camera model (ids 0 to {max(models)}); fix the camera row (or import "
                                "the images again)")
        model_name, nparams = models[model]
        if (nbytes or 0) != 8 * nparams:
            raise DatabaseError(f"database {name} is damaged: camera {camera_id} ({model_name}) holds "
                                f"{nbytes or 0} bytes of parameters, {8 * nparams} expected ({nparams} doubles); "
                                "fix the camera row (or import the images again)")


def _check_frames(p: Path, name: Path) -> None:
    """Refuse images with no frame, or frames with no rig (pycolmap would fail a check); raises
    :class:`DatabaseError`."""
    checks = (
        ("SELECT image_id, name FROM images WHERE image_id NOT IN "
         "(SELECT data_id FROM frame_data WHERE sensor_type = 0) ORDER BY image_id",
         "no row in frame_data"),
        ("SELECT i.image_id, i.name FROM images i JOIN frame_data d ON d.data_id = i.image_id AND d.sensor_type = 0 "
         "WHERE d.sensor_id != i.camera_id ORDER BY i.image_id", "a frame_data row naming another camera"),
        ("SELECT i.image_id, i.name FROM images i JOIN frame_data d ON d.data_id = i.image_id AND d.sensor_type = 0 "
         "WHERE d.frame_id NOT IN (SELECT frame_id FROM frames) ORDER BY i.image_id", "a frame with no row in frames"),
        ("SELECT i.image_id, i.name FROM images i JOIN frame_data d ON d.data_id = i.image_id AND d.sensor_type = 0 "
         "JOIN frames f ON f.frame_id = d.frame_id WHERE f.rig_id NOT IN (SELECT rig_id FROM rigs) "
         "ORDER BY i.image_id", "a frame whose rig has no row in rigs"),
    )
    con = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
    try:
        for query, what in checks:
            rows = con.execute(query).fetchall()
            if rows:
                shown = ", ".join(f"{n!r} (id {i})" for i, n in rows[:3]) + (
                    f" and {len(rows) - 3} more" if len(rows) > 3 else "")
                raise DatabaseError(f"database {name} is damaged: {len(rows)} image(s) with {what} (the rig and "
                                    f"frame tables): {shown}; import the images again (or repair those rows)")
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"not a COLMAP database ({exc}): {name}") from None
    finally:
        con.close()


#: (table, key column, bytes per value) of the array blobs pycolmap allocates by their
#: ``rows`` and ``cols`` columns (a lying ``rows`` makes it ask for terabytes).
_BLOB_TABLES = (("keypoints", "image_id", 4), ("matches", "pair_id", 4), ("two_view_geometries", "pair_id", 4))


def _check_blob_sizes(p: Path, name: Path) -> None:
    """Refuse array blobs that do not hold ``rows * cols`` values; raises :class:`DatabaseError`."""
    con = sqlite3.connect(f"file:{p.resolve()}?mode=ro", uri=True)
    try:
        for table, key, size in _BLOB_TABLES:
            bad = con.execute(
                f"SELECT {key}, rows, cols, length(data) FROM {table} WHERE rows < 0 OR cols < 0 OR "
                f"(rows > 0 AND (data IS NULL OR rows * cols * {size} != length(data))) LIMIT 1").fetchone()
            if bad is None:
                continue
            k, nrows, ncols, nbytes = bad
            where = f"image {k}" if key == "image_id" else "pair of images {} and {}".format(*image_pair(k))
            raise DatabaseError(f"database {name} is damaged: {table} of {where} says {nrows} x {ncols} values but "
                                f"holds {nbytes or 0} bytes; rebuild it (or restore a backup)")
    except sqlite3.DatabaseError as exc:
        raise DatabaseError(f"not a COLMAP database ({exc}): {name}") from None
    finally:
        con.close()


@dataclass(frozen=True)
class ImageRecord:
    """One image of the database: id, file name (relative to the image folder), camera size."""

    image_id: int
    name: str
    camera_id: int
    width: int
    height: int


@dataclass(frozen=True)
class PairRecord:
    """One image pair with its match count in the chosen source; image_id1 < image_id2."""

    image_id1: int
    image_id2: int
    num_matches: int


#: The two-view configurations of a verified pair (a model the mapper can use).
VERIFIED_CONFIGS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")


def is_verified(tvg) -> bool:
    """A ``pycolmap.TwoViewGeometry`` holds a verified model (:data:`VERIFIED_CONFIGS`)."""
    import pycolmap

    return pycolmap.TwoViewGeometryConfiguration(int(tvg.config)).name in VERIFIED_CONFIGS


def fitted_geometry(F: np.ndarray | None, H: np.ndarray | None):
    """A new ``pycolmap.TwoViewGeometry`` holding ``F`` (UNCALIBRATED), or else ``H`` (PLANAR)."""
    import pycolmap

    tvg = pycolmap.TwoViewGeometry()
    if F is not None:
        tvg.config, tvg.F = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED, F
    else:
        tvg.config, tvg.H = pycolmap.TwoViewGeometryConfiguration.PLANAR, H
    return tvg


def stored_model(handle, i: int, j: int):
    """The pair's stored ``pycolmap.TwoViewGeometry`` when it holds a verified model, else None."""
    tvg = handle.read_two_view_geometry(i, j) if handle.exists_two_view_geometry(i, j) else None
    return tvg if tvg is not None and is_verified(tvg) else None


def keep_or_fit(handle, i: int, j: int, inliers: np.ndarray, fit: Callable[[], Any], *, keep: bool = True):
    """The pair's stored verified model when ``keep`` and it has one, else ``fit()`` (None: no model)."""
    old = stored_model(handle, i, j) if keep else None
    tvg = old if old is not None else fit()
    if tvg is not None:
        tvg.inlier_matches = np.ascontiguousarray(inliers, np.uint32)
    return tvg


class ColmapDatabase(DatabaseBuilder):
    """A pycolmap handle on a working copy of a COLMAP database, with array helpers in colmap-miho's
    coordinates; matches are uint32 ``(M, 2)`` keypoint indices ordered (image_id1, image_id2)."""

    _db: Any  # pycolmap.Database while open, None once closed

    def __init__(self, path: str | Path) -> None:
        import pycolmap

        self.path = check_database_path(path)
        self._pycolmap = pycolmap
        self._db = pycolmap.Database.open(str(self.path))

    @classmethod
    def create(cls, path: str | Path) -> ColmapDatabase:
        """Create a NEW, empty database at ``path`` and open it; ``FileExistsError`` if it exists."""
        import pycolmap

        p = Path(path)
        if p.exists():
            raise FileExistsError(f"{p} exists: a new database is created only where none is")
        self = cls.__new__(cls)
        self.path, self._pycolmap = p, pycolmap
        self._db = pycolmap.Database.open(str(p))
        return self

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> None:
        db, self._db = self._db, None
        if db is None:
            return
        try:
            db.close()
        except RuntimeError:
            _never_free(db)  # its destructor would close it again, throw and abort the process
            raise

    def __enter__(self) -> ColmapDatabase:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def handle(self):
        """The underlying ``pycolmap.Database`` (open)."""
        if self._db is None:
            raise RuntimeError("database is closed")
        return self._db

    # -- reading ---------------------------------------------------------------------------
    def num_images(self) -> int:
        """Number of images in the database."""
        return int(self.handle.num_images())

    def num_verified_pairs(self) -> int:
        """Number of image pairs with a two-view geometry holding at least one inlier."""
        return int(self.handle.num_verified_image_pairs())

    def num_inlier_matches(self) -> int:
        """Total number of two-view-geometry inlier matches over all pairs."""
        return int(self.handle.num_inlier_matches())

    def images(self) -> list[ImageRecord]:
        """All images, sorted by id, with their camera's width and height in pixels."""
        cams = {c.camera_id: c for c in self.handle.read_all_cameras()}
        out = []
        for im in self.handle.read_all_images():
            cam = cams.get(im.camera_id)
            out.append(ImageRecord(int(im.image_id), str(im.name), int(im.camera_id),
                                   int(cam.width) if cam else 0, int(cam.height) if cam else 0))
        return sorted(out, key=lambda r: r.image_id)

    def verified_model(self, i: int, j: int):
        """The pair's stored ``pycolmap.TwoViewGeometry`` when it holds a verified model, else None."""
        return stored_model(self.handle, int(i), int(j))

    def raw_keypoints(self, image_id: int) -> np.ndarray:
        """The stored keypoint rows, float32 (N, C), C in {2, 4, 6}, COLMAP coordinates."""
        kp = np.asarray(self.handle.read_keypoints(int(image_id)), dtype=np.float32)
        if kp.ndim != 2 or kp.shape[0] == 0:
            return np.zeros((0, 2), np.float32)
        return kp

    def keypoints(self, image_id: int) -> np.ndarray:
        """Keypoint positions of one image, float64 (N, 2), integer = pixel centre."""
        return colmap_to_pixel_centre(self.raw_keypoints(image_id)[:, :2])

    def keypoint_affines(self, image_id: int) -> np.ndarray | None:
        """Local affine frames ``(N, 2, 2)`` (columns = local axes, pixels) from 6 (SIFT) or 4
        (scale, orientation) columns, or None for x, y only."""
        raw = self.raw_keypoints(image_id)
        if raw.shape[1] >= 6:  # the four columns alone: a view would hold all six in float64
            return raw[:, 2:6].astype(np.float64).reshape(-1, 2, 2)
        raw = raw.astype(np.float64)
        if raw.shape[1] == 4:
            s, o = raw[:, 2], raw[:, 3]
            c, n = s * np.cos(o), s * np.sin(o)
            return np.stack([np.stack([c, -n], -1), np.stack([n, c], -1)], 1)
        return None

    def pairs(self, source: MatchSource | str) -> list[PairRecord]:
        """Pairs with matches in ``source`` ("verified" or "raw"), sorted by pair id; reads counts only."""
        source = MatchSource.parse(source, "source")
        if source == MatchSource.VERIFIED:
            pids, counts = self.handle.read_two_view_geometry_num_inliers()
        else:
            pids, counts = self.handle.read_num_matches()
        out = []
        for pid, n in sorted(zip(pids, counts, strict=True)):
            i, j = image_pair(pid)
            if n > 0:
                out.append(PairRecord(i, j, int(n)))
        return out

    def matches(self, image_id1: int, image_id2: int, source: MatchSource | str) -> np.ndarray:
        """One pair's matches, uint32 ``(M, 2)``; a repeated row is kept once, with a warning."""
        source = MatchSource.parse(source, "source")
        if source == MatchSource.VERIFIED:
            m = self.handle.read_two_view_geometry(int(image_id1), int(image_id2)).inlier_matches
        else:
            m = self.handle.read_matches(int(image_id1), int(image_id2))
        m = np.asarray(m, dtype=np.uint32).reshape(-1, 2)
        if len(m) > 1:  # a repeated (i, j) row would count twice in the filter and be written back
            _, first = np.unique((m[:, 0].astype(np.uint64) << np.uint64(32)) | m[:, 1], return_index=True)
            if len(first) < len(m):
                # said once per database (a damaged one has many), the rest at -v; dropping a
                # repeat changes nothing a mapper would use, so it is no warning
                level = logging.DEBUG if getattr(self, "_warned_repeats", False) else logging.INFO
                self._warned_repeats = True
                log.log(level, "image pair %d-%d: %d repeated rows in its %s matches, counted once%s", image_id1,
                        image_id2, len(m) - len(first), source,
                        "" if level == logging.DEBUG else " (other pairs with repeated rows: see -v)")
                m = m[np.sort(first)]
        return m

    # -- writing ---------------------------------------------------------------------------
    def write_keypoints(self, image_id: int, xy: np.ndarray, moved: np.ndarray) -> int:
        """Write ``xy`` float ``(N, 2)`` for the ``moved`` rows only; every other value is written
        back bit-identical. Returns the number of rows changed."""
        raw = self.raw_keypoints(image_id)
        xy = np.asarray(xy, dtype=np.float64)
        moved = np.asarray(moved, dtype=bool)
        if xy.shape != (raw.shape[0], 2) or moved.shape != (raw.shape[0],):
            raise InvalidInput(
                f"image {image_id}: xy must be ({raw.shape[0]}, 2) and moved ({raw.shape[0]},), "
                f"got {xy.shape} and {moved.shape}"
            )
        if not moved.any():
            return 0
        new = raw.copy()
        new[moved, :2] = pixel_centre_to_colmap(xy[moved]).astype(np.float32)
        self.handle.update_keypoints(int(image_id), new)
        return int(moved.sum())

    def write_pair(self, image_id1: int, image_id2: int, kept: np.ndarray,
                   xy1: np.ndarray, xy2: np.ndarray, *, keep_model: bool = True) -> str:
        """Write a pair's kept matches ``(K, 2)`` and its geometry: the verified model when
        ``keep_model``, else F (or H) fitted to ``xy1``, ``xy2``; returns the config name written."""
        db = self.handle
        i, j = int(image_id1), int(image_id2)
        kept = np.ascontiguousarray(kept, dtype=np.uint32).reshape(-1, 2)
        if db.exists_matches(i, j):
            db.delete_matches(i, j)
        db.write_matches(i, j, kept)
        existed = db.exists_two_view_geometry(i, j)
        if len(kept) == 0:
            if existed:
                db.delete_two_view_geometry(i, j)
            return "NONE"
        tvg = keep_or_fit(db, i, j, kept, lambda: fitted_geometry(*fit_model_lsq(pixel_centre_to_colmap(xy1),
                                                                                 pixel_centre_to_colmap(xy2))),
                          keep=keep_model)
        if existed:
            db.update_two_view_geometry(i, j, tvg)
        else:
            db.write_two_view_geometry(i, j, tvg)
        return self._pycolmap.TwoViewGeometryConfiguration(int(tvg.config)).name

    def write_scene_copy(self, path: str | Path, matches: Mapping[Pair, np.ndarray],
                         fit: Callable[[int, int, np.ndarray], Any], *,
                         matched_keypoints_only: bool = False) -> dict[int, np.ndarray] | None:
        """A NEW database at ``path`` for a mapper: this one's cameras, rigs, frames, images (ids
        kept, each named by its id: a mapper joins names to its folder) and keypoints, and each
        pair of ``matches`` (``(M, 2)`` keypoint indices) with them as its two-view geometry's
        inliers: its verified model kept, else ``fit(i, j, m)`` (a ``pycolmap.TwoViewGeometry``;
        a pair with neither is left out).

        With ``matched_keypoints_only`` an image keeps only the keypoints that ``matches`` use,
        in their order (a mapper holds every keypoint it is given: on a sample of the matches
        most of its memory); returns then image id -> the indices here of the keypoints
        written, ascending (keypoint ``k`` of the copy is ``indices[k]`` here), else None."""
        h = self.handle
        kept: dict[int, np.ndarray] | None = None
        if matched_keypoints_only:
            ends: dict[int, list[np.ndarray]] = {}
            for (i, j), m in matches.items():
                ends.setdefault(i, []).append(np.asarray(m[:, 0], np.int64))
                ends.setdefault(j, []).append(np.asarray(m[:, 1], np.int64))
            kept = {int(rec.image_id): np.unique(np.concatenate(ends[rec.image_id])) if rec.image_id in ends
                    else np.zeros(0, np.int64) for rec in self.images()}
        with self._pycolmap.Database.open(str(path)) as dst:
            for cam in h.read_all_cameras():
                dst.write_camera(cam, use_camera_id=True)
            for rig in h.read_all_rigs():
                dst.write_rig(rig, use_rig_id=True)
            for frame in h.read_all_frames():
                dst.write_frame(frame, use_frame_id=True)
            for im in h.read_all_images():
                im.name = f"{int(im.image_id)}"
                dst.write_image(im, use_image_id=True)
            for rec in self.images():
                i = int(rec.image_id)
                kps = h.read_keypoints(i)
                dst.write_keypoints(i, np.ascontiguousarray(kps if kept is None else kps[kept[i]], np.float32))
            for (i, j), m in sorted(matches.items()):
                tvg = keep_or_fit(h, i, j, m, functools.partial(fit, i, j, m))
                if tvg is not None:
                    if kept is not None:
                        m = np.column_stack([np.searchsorted(kept[i], m[:, 0]), np.searchsorted(kept[j], m[:, 1])])
                        tvg.inlier_matches = np.ascontiguousarray(m, np.uint32)
                    dst.write_matches(i, j, np.ascontiguousarray(m, np.uint32))
                    dst.write_two_view_geometry(i, j, tvg)
        return kept

    def delete_two_view_geometries(self, pairs: list[Pair]) -> None:
        """Delete the two-view geometry rows of ``pairs`` (before COLMAP re-verification)."""
        for i, j in pairs:
            if self.handle.exists_two_view_geometry(int(i), int(j)):
                self.handle.delete_two_view_geometry(int(i), int(j))

    @contextlib.contextmanager
    def transaction(self):
        """A pycolmap transaction (speed only: it commits even when the block raises). If the commit
        fails, the handle is never freed: its C++ destructor would retry, throw and abort the
        process."""
        tx = self._pycolmap.DatabaseTransaction(self.handle)
        tx.__enter__()
        try:
            yield tx
        except BaseException:
            self._end_transaction(tx, reraise=False)  # the block's own error is the one raised
            raise
        self._end_transaction(tx, reraise=True)

    def _end_transaction(self, tx: Any, *, reraise: bool) -> None:
        """Commit (or roll back) ``tx``; on failure keep it alive and raise only if ``reraise``."""
        try:
            tx.__exit__(None, None, None)
        except RuntimeError:
            _never_free(tx)
            _never_free(self._db)
            if reraise:
                raise


def _never_free(obj) -> None:
    """Keep ``obj`` alive until exit: pycolmap's destructor would retry a failed write and abort."""
    import ctypes

    if obj is not None:
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))


def count_images(path: str | Path) -> int:
    """Number of images in the database at ``path`` (never the user's file: pycolmap migrates it)."""
    with ColmapDatabase(path) as db:
        return int(db.handle.num_images())


def verify_geometry(path: str | Path, *, seed: int = 0) -> None:
    """COLMAP's geometric verification of every matched pair at ``path``, seeded with ``seed``."""
    import pycolmap

    opts = pycolmap.TwoViewGeometryOptions()
    opts.ransac.random_seed = int(seed)
    pycolmap.geometric_verification(str(path), two_view_geometry_options=opts)


def write_camera_intrinsics(path: str | Path, intrinsics: CameraIntrinsics | dict[str, CameraIntrinsics]) -> int:
    """Set the model and parameters of cameras in the working copy at ``path`` (one for all, or
    image name -> intrinsics), as a prior focal; returns how many. DatabaseError for conflicting or
    mis-sized cameras, ValueError for a bad model or parameter count."""
    with ColmapDatabase(path) as db:
        cameras = {int(c.camera_id): c for c in db.handle.read_all_cameras()}
        wanted: dict[int, CameraIntrinsics] = {}
        if isinstance(intrinsics, CameraIntrinsics):
            wanted = dict.fromkeys(cameras, intrinsics)
        else:
            for image in db.handle.read_all_images():
                intr = intrinsics.get(image.name)
                if intr is None:
                    continue
                cam = int(image.camera_id)
                if cam in wanted and wanted[cam] != intr:
                    raise DatabaseError(f"camera {cam} is shared by images with different intrinsics "
                                        f"(e.g. {image.name}); extract with one camera per image")
                wanted[cam] = intr
        new = {cam: camera_from(cameras[cam], intr) for cam, intr in wanted.items()}
        for camera in new.values():
            db.handle.update_camera(camera)
    log.debug("wrote the intrinsics of %d camera(s) into %s", len(new), path)
    return len(new)
