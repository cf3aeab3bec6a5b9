"""Filling a new COLMAP database (hloc import, synthetic scenes): cameras, rigs, images with
their frames, keypoints and matches, through the open pycolmap handle of
:class:`~colmap_miho.adapters.database.ColmapDatabase` (which opens and closes it).

Coordinates in are colmap-miho's (integer = pixel centre) unless said otherwise; the +0.5 shift
to COLMAP's convention is :func:`~colmap_miho.adapters.conventions.pixel_centre_to_colmap`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInput
from .conventions import image_pair, pixel_centre_to_colmap


class DatabaseBuilder:
    """The building methods of :class:`~colmap_miho.adapters.database.ColmapDatabase`, which
    provides ``handle`` (the open ``pycolmap.Database``), ``_pycolmap``, ``images()`` and
    ``raw_keypoints()``."""

    _pycolmap: Any

    @property
    def handle(self) -> Any:  # pragma: no cover - provided by ColmapDatabase
        raise NotImplementedError

    def images(self) -> list[Any]:  # pragma: no cover - provided by ColmapDatabase
        raise NotImplementedError

    def raw_keypoints(self, image_id: int) -> np.ndarray:  # pragma: no cover - provided by ColmapDatabase
        raise NotImplementedError

    def add_camera(self, model: str, width: int, height: int, focal: float) -> tuple[int, int]:
        """Write a camera of COLMAP model ``model`` (``focal`` prior in pixels, pycolmap's
        default principal point and distortion) and a rig with it as reference sensor.

        Returns:
            ``(camera_id, rig_id)``.

        Raises:
            ValueError: ``model`` is not a COLMAP camera model (the message names it).
        """
        pc = self._pycolmap
        try:
            cam = pc.Camera.create_from_model_name(0, model, float(focal), int(width), int(height))
        except ValueError:
            raise InvalidInput(f"camera_model={model!r} is not a COLMAP camera model "
                             "(e.g. SIMPLE_RADIAL, PINHOLE, OPENCV)") from None
        camera_id = self.handle.write_camera(cam)
        rig = pc.Rig()
        rig.add_ref_sensor(pc.sensor_t(pc.SensorType.CAMERA, camera_id))
        return int(camera_id), int(self.handle.write_rig(rig))

    def add_image(self, name: str, camera_id: int, rig_id: int) -> int:
        """Write image ``name`` (path relative to the image folder) of camera ``camera_id`` and
        its frame in rig ``rig_id``; returns the new image id."""
        pc = self._pycolmap
        image_id = self.handle.write_image(pc.Image(name=name, camera_id=int(camera_id)))
        frame = pc.Frame()
        frame.rig_id = int(rig_id)
        frame.add_data_id(pc.data_t(pc.sensor_t(pc.SensorType.CAMERA, int(camera_id)), image_id))
        self.handle.write_frame(frame)
        return int(image_id)

    def add_keypoints(self, image_id: int, xy: np.ndarray, affines: np.ndarray | None = None, *,
                      colmap_coordinates: bool = False) -> None:
        """Write the keypoints of a new image as COLMAP's 6 columns (x, y, a11, a12, a21, a22).

        Args:
            xy: float (N, 2) positions, integer = pixel centre (shifted by +0.5 here), or
                already in COLMAP's convention when ``colmap_coordinates``.
            affines: float (N, 2, 2) local affine frames (columns = local axes, pixels), or
                None for the identity.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        rows = np.zeros((len(xy), 6), dtype=np.float32)
        rows[:, :2] = xy if colmap_coordinates else pixel_centre_to_colmap(xy)
        if affines is not None:
            rows[:, 2:] = np.asarray(affines, dtype=np.float32).reshape(-1, 4)
        else:
            rows[:, 2], rows[:, 5] = 1.0, 1.0
        self.handle.write_keypoints(int(image_id), rows)

    def add_matches(self, image_id1: int, image_id2: int, matches: np.ndarray, *,
                    as_inliers: bool = False) -> None:
        """Write the matches of a new pair, uint32 (M, 2) keypoint indices ordered
        (image_id1, image_id2); ``as_inliers`` also stores them all as the inliers of an
        UNCALIBRATED two-view geometry (no verification)."""
        m = np.ascontiguousarray(matches, dtype=np.uint32).reshape(-1, 2)
        self.handle.write_matches(int(image_id1), int(image_id2), m)
        if as_inliers:
            tvg = self._pycolmap.TwoViewGeometry()
            tvg.config = self._pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            tvg.inlier_matches = m
            self.handle.write_two_view_geometry(int(image_id1), int(image_id2), tvg)

    def synthesize(self, dataset_options, noise_options=None):
        """Fill this new database with ``pycolmap.synthesize_dataset(dataset_options)``.

        With ``noise_options`` (``pycolmap.SyntheticNoiseOptions``) the stored keypoints are
        then moved by ``pycolmap.synthesize_noise``.

        Returns:
            The noise-free ground-truth ``pycolmap.Reconstruction`` (COLMAP coordinates).
        """
        pc = self._pycolmap
        rec = pc.synthesize_dataset(dataset_options, self.handle)
        gt = pc.Reconstruction(rec)
        if noise_options is not None:
            pc.synthesize_noise(noise_options, rec, self.handle)
        return gt

    def store_raw_matches_as_inliers(self) -> None:
        """Make every pair's two-view-geometry inliers equal to its raw ``matches`` (as a weak
        geometric verification would); the pairs must have a two-view geometry already."""
        pids, arrays = self.handle.read_all_matches()
        for pid, m in zip(pids, arrays, strict=True):
            i, j = image_pair(pid)
            tvg = self.handle.read_two_view_geometry(i, j)
            tvg.inlier_matches = np.asarray(m, np.uint32)
            self.handle.update_two_view_geometry(i, j, tvg)

    def keep_keypoint_columns(self, columns: int) -> None:
        """Rewrite every image's keypoints with their first ``columns`` columns (2, 4 or 6)."""
        if columns not in (2, 4, 6):
            raise InvalidInput(f"columns must be 2, 4 or 6, got {columns}")
        for record in self.images():
            kp = self.raw_keypoints(record.image_id)
            self.handle.update_keypoints(record.image_id, np.ascontiguousarray(kp[:, :columns]))
