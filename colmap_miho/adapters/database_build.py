"""Filling a new COLMAP database (hloc import, synthetic scenes) through the open handle of
:class:`~colmap_miho.adapters.database.ColmapDatabase`; coordinates in are colmap-miho's."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInput
from .conventions import image_pair, pixel_centre_to_colmap


class DatabaseBuilder:
    """The building methods of :class:`~colmap_miho.adapters.database.ColmapDatabase`."""

    _pycolmap: Any

    @property
    def handle(self) -> Any:  # pragma: no cover - provided by ColmapDatabase
        raise NotImplementedError

    def images(self) -> list[Any]:  # pragma: no cover - provided by ColmapDatabase
        raise NotImplementedError

    def raw_keypoints(self, image_id: int) -> np.ndarray:  # pragma: no cover - provided by ColmapDatabase
        raise NotImplementedError

    def add_camera(self, model: str, width: int, height: int, focal: float) -> tuple[int, int]:
        """Write a camera of ``model`` (``focal`` prior in pixels) and a rig with it; returns
        ``(camera_id, rig_id)``. ValueError for an unknown model."""
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
        """Write image ``name`` of ``camera_id`` and its frame in ``rig_id``; returns its id."""
        pc = self._pycolmap
        image_id = self.handle.write_image(pc.Image(name=name, camera_id=int(camera_id)))
        frame = pc.Frame()
        frame.rig_id = int(rig_id)
        frame.add_data_id(pc.data_t(pc.sensor_t(pc.SensorType.CAMERA, int(camera_id)), image_id))
        self.handle.write_frame(frame)
        return int(image_id)

    def add_keypoints(self, image_id: int, xy: np.ndarray, affines: np.ndarray | None = None, *,
                      colmap_coordinates: bool = False) -> None:
        """Write a new image's keypoints as COLMAP's 6 columns: ``xy`` ``(N, 2)`` (shifted +0.5
        unless ``colmap_coordinates``), ``affines`` ``(N, 2, 2)`` or None for identity."""
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
        """Write a new pair's matches ``(M, 2)``; ``as_inliers`` also stores them as UNCALIBRATED inliers."""
        m = np.ascontiguousarray(matches, dtype=np.uint32).reshape(-1, 2)
        self.handle.write_matches(int(image_id1), int(image_id2), m)
        if as_inliers:
            tvg = self._pycolmap.TwoViewGeometry()
            tvg.config = self._pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            tvg.inlier_matches = m
            self.handle.write_two_view_geometry(int(image_id1), int(image_id2), tvg)

    def synthesize(self, dataset_options, noise_options=None):
        """Fill this new database with ``pycolmap.synthesize_dataset`` (and ``synthesize_noise``
        with ``noise_options``); returns the noise-free ground truth (COLMAP coordinates)."""
        pc = self._pycolmap
        rec = pc.synthesize_dataset(dataset_options, self.handle)
        gt = pc.Reconstruction(rec)
        if noise_options is not None:
            pc.synthesize_noise(noise_options, rec, self.handle)
        return gt

    def store_raw_matches_as_inliers(self) -> None:
        """Make every pair's inliers equal to its raw matches (pairs need a two-view geometry)."""
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
