"""A synthetic COLMAP scene with ground truth, rendered images and planted errors.

Built entirely with pycolmap (offline, CPU, about a second): ``synthesize_dataset`` writes
cameras, images, keypoints and exhaustive matches; ``inlier_match_ratio`` plants outlier
matches; ``synthesize_noise`` moves the stored keypoints off their true projections;
``synthesize_images`` renders an image with a small textured blob at the true projection of
every 3D point. The ground-truth reconstruction keeps the noise-free positions.

Used by the tests of ``refine`` and of the mapping/report commands.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .database import ColmapDatabase, colmap_to_pixel_centre

log = logging.getLogger(__name__)


@dataclass
class SyntheticScene:
    """What :func:`make_synthetic_scene` built.

    Attributes:
        database: path of the COLMAP database (keypoints with noise, matches with outliers).
        image_dir: folder with the rendered images (names as in the database).
        gt_reconstruction: ``pycolmap.Reconstruction`` with the true poses and noise-free
            2D observations (COLMAP coordinates, as pycolmap stores them).
        gt_keypoints: image_id -> float64 (N, 2) true position of every stored keypoint,
            integer = pixel centre; NaN for keypoints that see no 3D point.
        point3D_ids: image_id -> int64 (N,) 3D point seen by each keypoint, -1 for none.
    """

    database: Path
    image_dir: Path
    gt_reconstruction: object
    gt_keypoints: dict[int, np.ndarray] = field(default_factory=dict)
    point3D_ids: dict[int, np.ndarray] = field(default_factory=dict)

    def is_true_match(self, image_id1: int, image_id2: int, matches: np.ndarray) -> np.ndarray:
        """bool (M,): whether each match (keypoint indices, (M, 2)) joins two observations
        of the same 3D point."""
        m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        a = self.point3D_ids[int(image_id1)][m[:, 0]]
        b = self.point3D_ids[int(image_id2)][m[:, 1]]
        return (a >= 0) & (a == b)


def make_synthetic_scene(
    out_dir: str | Path,
    *,
    num_images: int = 6,
    num_points: int = 300,
    outlier_ratio: float = 0.2,
    noise_px: float = 1.0,
    width: int = 640,
    height: int = 480,
    focal: float | None = None,
    keypoint_columns: int = 6,
    outliers_in_verified: bool = True,
    render_images: bool = True,
    seed: int = 0,
) -> SyntheticScene:
    """Create ``out_dir/database.db`` and ``out_dir/images/`` for a synthetic scene.

    Args:
        out_dir: folder to write into (created; ``database.db`` must not exist yet).
        num_images: images, one camera each position, all of size ``width`` x ``height``.
        num_points: 3D points (each seen by every image it projects into).
        outlier_ratio: fraction of wrong matches planted in every pair, in [0, 1).
        noise_px: standard deviation of the Gaussian noise added to the stored keypoints,
            in pixels (the rendered images keep the true positions).
        focal: focal length in pixels (default 1.2 * width).
        keypoint_columns: 2, 4 or 6 stored keypoint columns (COLMAP SIFT has 6).
        outliers_in_verified: also store the planted outliers as two-view-geometry inliers
            (as a weak geometric verification would), not only in the ``matches`` table.
        render_images: write the images (skip for database-only tests).
        seed: pycolmap's random seed (pycolmap keeps one global generator).

    Returns:
        A :class:`SyntheticScene`.

    Raises:
        ValueError: an argument out of range; the message names it.
    """
    import pycolmap

    if num_images < 2:
        raise ValueError(f"num_images must be >= 2, got {num_images}")
    if num_points < 8:
        raise ValueError(f"num_points must be >= 8, got {num_points}")
    if not 0 <= outlier_ratio < 1:
        raise ValueError(f"outlier_ratio must be in [0, 1), got {outlier_ratio}")
    if noise_px < 0:
        raise ValueError(f"noise_px must be >= 0, got {noise_px}")
    if keypoint_columns not in (2, 4, 6):
        raise ValueError(f"keypoint_columns must be 2, 4 or 6, got {keypoint_columns}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    database = out / "database.db"
    if database.exists():
        raise ValueError(f"out_dir already holds a database: {database}")
    image_dir = out / "images"
    image_dir.mkdir(exist_ok=True)

    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs = 1
    opts.num_cameras_per_rig = 1
    opts.num_frames_per_rig = int(num_images)
    opts.num_points3D = int(num_points)
    opts.camera_width = int(width)
    opts.camera_height = int(height)
    opts.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    f = float(focal) if focal else 1.2 * width
    opts.camera_params = [f, width / 2.0, height / 2.0, 0.0]
    opts.inlier_match_ratio = 1.0 - float(outlier_ratio)
    opts.num_points2D_without_point3D = 10

    pycolmap.set_random_seed(int(seed))
    noise = pycolmap.SyntheticNoiseOptions(point2D_stddev=float(noise_px)) if noise_px > 0 else None
    with ColmapDatabase.create(database) as db:
        gt = db.synthesize(opts, noise)
        if outliers_in_verified:
            db.store_raw_matches_as_inliers()
        if keypoint_columns != 6:
            db.keep_keypoint_columns(keypoint_columns)
        stored = {r.image_id: len(db.raw_keypoints(r.image_id)) for r in db.images()}

    gt_kp: dict[int, np.ndarray] = {}
    ids: dict[int, np.ndarray] = {}
    for image_id, image in gt.images.items():
        n = stored[image_id]
        xy = np.full((n, 2), np.nan)
        pid3 = np.full(n, -1, dtype=np.int64)
        for k, p2 in enumerate(image.points2D[:n]):
            if p2.has_point3D():
                xy[k] = p2.xy
                pid3[k] = p2.point3D_id
        gt_kp[int(image_id)] = colmap_to_pixel_centre(xy)
        ids[int(image_id)] = pid3
    if render_images:
        pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), gt, str(image_dir))
    log.debug("synthetic scene with %d images, %d points in %s", num_images, num_points, out)
    return SyntheticScene(database, image_dir, gt, gt_kp, ids)
