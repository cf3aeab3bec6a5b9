"""A synthetic COLMAP scene with ground truth, rendered images and planted errors.

Built entirely with pycolmap (offline, CPU, about a second): ``synthesize_dataset`` writes
cameras, images, keypoints and exhaustive matches; ``inlier_match_ratio`` plants outlier
matches; ``synthesize_noise`` moves the stored keypoints off their true projections;
``synthesize_images`` renders an image with a small textured blob at the true projection of
every 3D point. The ground-truth reconstruction keeps the noise-free positions.

Used by the tests of ``refine`` and of the mapping/report commands.

pycolmap's synthesizer puts every camera on a sphere looking at every point, so each point is
seen by every image (a 50-image scene gives 50-image tracks), and its pair graphs are
exhaustive, a chain of consecutive image ids, or random. :func:`make_survey_scene` builds what
a large photo collection looks like instead: an aerial survey (serpentine flight lines over a
gently rolling terrain, given forward and side overlap), so a point is seen by the few images
around it, and a pair graph of sequential neighbours plus k nearest camera centres, the way
COLMAP's sequential / spatial matchers choose pairs. The images are rendered by
``pycolmap.synthesize_images`` from the same ground truth.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from colmap_miho.adapters.conventions import colmap_to_pixel_centre
from colmap_miho.adapters.database import ColmapDatabase

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
        pairs: the matched image-id pairs (i < j), when the builder chose a pair graph
            (:func:`make_survey_scene`); empty for exhaustive scenes.
    """

    database: Path
    image_dir: Path
    gt_reconstruction: object
    gt_keypoints: dict[int, np.ndarray] = field(default_factory=dict)
    point3D_ids: dict[int, np.ndarray] = field(default_factory=dict)
    pairs: list[tuple[int, int]] = field(default_factory=list)

    def is_true_match(self, image_id1: int, image_id2: int, matches: np.ndarray) -> np.ndarray:
        """bool (M,): whether each match (keypoint indices, (M, 2)) joins two observations
        of the same 3D point."""
        m = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        a = self.point3D_ids[int(image_id1)][m[:, 0]]
        b = self.point3D_ids[int(image_id2)][m[:, 1]]
        return (a >= 0) & (a == b)


def _gt_keypoints(gt, stored: dict[int, int]) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Per image: true keypoint positions (integer = pixel centre, NaN without a 3D point)
    and the 3D point id of each of the first ``stored[image_id]`` points2D (-1 for none)."""
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
    return gt_kp, ids


def _check_noise(outlier_ratio: float, noise_px: float) -> None:
    if not 0 <= outlier_ratio < 1:
        raise ValueError(f"outlier_ratio must be in [0, 1), got {outlier_ratio}")
    if noise_px < 0:
        raise ValueError(f"noise_px must be >= 0, got {noise_px}")


def _scene_folder(out_dir: str | Path) -> tuple[Path, Path]:
    """``out_dir/database.db`` (must not exist yet) and ``out_dir/images/`` (created)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    database = out / "database.db"
    if database.exists():
        raise ValueError(f"out_dir already holds a database: {database}")
    image_dir = out / "images"
    image_dir.mkdir(exist_ok=True)
    return database, image_dir


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
    _check_noise(outlier_ratio, noise_px)
    if keypoint_columns not in (2, 4, 6):
        raise ValueError(f"keypoint_columns must be 2, 4 or 6, got {keypoint_columns}")
    database, image_dir = _scene_folder(out_dir)

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

    gt_kp, ids = _gt_keypoints(gt, stored)
    if render_images:
        pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), gt, str(image_dir))
    log.debug("synthetic scene with %d images, %d points in %s", num_images, num_points, database.parent)
    return SyntheticScene(database, image_dir, gt, gt_kp, ids)


# ------------------------------------------------------------------ aerial survey (large scenes)
@dataclass(frozen=True)
class SurveyLayout:
    """Cameras and 3D points of an aerial survey (world: x east, y north, z up, flight height 1).

    Attributes:
        centres: float64 (N, 3) camera centres in flight order (serpentine lines along y).
        rotations: float64 (N, 3, 3) cam_from_world rotations (camera looking down, image x
            east, image y south, plus a small random tilt).
        points: float64 (P, 3) terrain points.
        focal, width, height: pinhole intrinsics in pixels (principal point at the image
            centre, COLMAP's convention: (0, 0) is the top-left pixel's corner).
        lines: number of flight lines.
    """

    centres: np.ndarray
    rotations: np.ndarray
    points: np.ndarray
    focal: float
    width: int
    height: int
    lines: int

    def project(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Points visible in image ``index``: (point indices int64 (K,), xy float64 (K, 2) in
        COLMAP coordinates), those in front of the camera and inside the image."""
        cam = (self.points - self.centres[index]) @ self.rotations[index].T
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.focal * cam[:, 0] / z + self.width / 2.0
            v = self.focal * cam[:, 1] / z + self.height / 2.0
        ok = (z > 0) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        idx = np.flatnonzero(ok)
        return idx, np.stack([u[idx], v[idx]], axis=1)

    def intrinsics(self) -> np.ndarray:
        """float64 (3, 3) calibration matrix K in COLMAP coordinates (principal point at the
        image centre)."""
        return np.array([[self.focal, 0.0, self.width / 2.0], [0.0, self.focal, self.height / 2.0],
                         [0.0, 0.0, 1.0]])

    def relative_geometry(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """The true two-view geometry of images ``a`` -> ``b`` (0-based): float64 (3, 3) ``E``
        (unit-norm baseline; ``x_b^T E x_a = 0`` for normalised image points) and ``F``
        (``x_b^T F x_a = 0`` for COLMAP pixel coordinates, Frobenius norm 1), as COLMAP stores
        them for the pair (a, b)."""
        Ra, Rb = self.rotations[a], self.rotations[b]
        R = Rb @ Ra.T  # cam_b from cam_a
        t = Rb @ (self.centres[a] - self.centres[b])
        t = t / np.linalg.norm(t)
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        E = tx @ R
        Kinv = np.linalg.inv(self.intrinsics())
        F = Kinv.T @ E @ Kinv
        return E, F / np.linalg.norm(F)


def _small_rotation(rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    """A random rotation of angle ~ N(0, sigma_deg) degrees about a uniform axis (Rodrigues)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.normal(0.0, sigma_deg)) if sigma_deg > 0 else 0.0
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def survey_layout(num_images: int, *, width: int = 1024, height: int = 768, focal: float | None = None,
                  forward_overlap: float = 0.7, side_overlap: float = 0.4, points_per_image: int = 300,
                  relief: float = 0.1, tilt_deg: float = 2.0, seed: int = 0) -> SurveyLayout:
    """Plan an aerial survey of ``num_images`` images over a roughly square area.

    Flight lines run along y, ``forward_overlap`` of an image's height shared with the next
    image, ``side_overlap`` of its width with the next line; images are numbered along a
    serpentine path. Terrain points are uniform in x, y (``points_per_image`` per image
    footprint, on average) at height ``relief`` * sin-waves (flight height 1). A point is seen
    by about 1 / ((1 - forward_overlap) (1 - side_overlap)) images.

    Raises:
        ValueError: an argument out of range; the message names it.
    """
    if num_images < 2:
        raise ValueError(f"num_images must be >= 2, got {num_images}")
    for name, val in (("forward_overlap", forward_overlap), ("side_overlap", side_overlap)):
        if not 0 <= val < 1:
            raise ValueError(f"{name} must be in [0, 1), got {val}")
    if points_per_image < 8:
        raise ValueError(f"points_per_image must be >= 8, got {points_per_image}")
    if not 0 <= relief < 0.5:
        raise ValueError(f"relief must be in [0, 0.5) (of the flight height), got {relief}")
    rng = np.random.default_rng(seed)
    f = float(focal) if focal else 1.2 * width
    foot_w, foot_h = width / f, height / f  # ground footprint at z = 0, flight height 1
    step_fwd, step_side = foot_h * (1 - forward_overlap), foot_w * (1 - side_overlap)
    lines = max(1, int(round(np.sqrt(num_images * step_fwd / step_side))))
    per_line = int(np.ceil(num_images / lines))
    centres = np.zeros((num_images, 3))
    for k in range(num_images):
        line, pos = divmod(k, per_line)
        if line % 2:
            pos = per_line - 1 - pos
        centres[k] = (line * step_side, pos * step_fwd, 1.0)
    centres[:, :2] += rng.normal(0.0, 0.05, (num_images, 2)) * (step_fwd, step_side)
    centres[:, 2] += rng.normal(0.0, 0.02, num_images)
    base = np.diag([1.0, -1.0, -1.0])  # camera x east, y south, z down
    rotations = np.stack([_small_rotation(rng, tilt_deg) @ base for _ in range(num_images)])

    lo = centres[:, :2].min(0) - (foot_w / 2, foot_h / 2)
    hi = centres[:, :2].max(0) + (foot_w / 2, foot_h / 2)
    n_points = int(round(points_per_image * np.prod(hi - lo) / (foot_w * foot_h)))
    xy = rng.uniform(lo, hi, (n_points, 2))
    phase = rng.uniform(0, 2 * np.pi, 3)
    wave = 2 * np.pi / (3 * foot_w)
    z = relief * 0.5 * (np.sin(wave * xy[:, 0] + phase[0]) * np.cos(wave * xy[:, 1] + phase[1])
                        + np.sin(0.7 * wave * (xy[:, 0] + xy[:, 1]) + phase[2]))
    points = np.column_stack([xy, z])
    return SurveyLayout(centres, rotations, points, f, int(width), int(height), lines)


def survey_pairs(centres: np.ndarray, *, sequential: int = 2, nearest: int = 6) -> list[tuple[int, int]]:
    """The pair graph of a photo sequence: each image with its next ``sequential`` images in
    capture order and with its ``nearest`` nearest camera centres (Euclidean). Returns sorted
    0-based index pairs (i < j), each once."""
    n = len(centres)
    if sequential < 0 or nearest < 0:
        raise ValueError(f"sequential and nearest must be >= 0, got {sequential}, {nearest}")
    pairs = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + sequential))}
    if nearest > 0 and n > 1:
        from scipy.spatial import cKDTree

        k = min(nearest + 1, n)
        _, nn = cKDTree(centres).query(centres, k=k)
        for i, row in enumerate(np.asarray(nn).reshape(n, k)):
            pairs.update((min(i, int(j)), max(i, int(j))) for j in row if int(j) != i)
    return sorted(pairs)


def write_survey_database(database: Path, layout: SurveyLayout, keypoints: dict[int, np.ndarray],
                          matches: dict[tuple[int, int], np.ndarray],
                          fundamental: dict[tuple[int, int], np.ndarray] | None = None) -> None:
    """A new COLMAP database of a survey: one SIMPLE_RADIAL camera (no distortion, the
    layout's focal), images ``survey_00000.png``... with ids 1..N, ``keypoints`` (image id ->
    (N, 2) COLMAP coordinates) and ``matches`` ((i, j) -> (M, 2)) stored as the inliers of an
    UNCALIBRATED geometry too, with the pair's ``fundamental`` matrix where given (else none:
    a mapper then decomposes an empty model)."""
    with ColmapDatabase.create(database) as db, db.transaction():
        camera_id, rig_id = db.add_camera("SIMPLE_RADIAL", layout.width, layout.height, layout.focal)
        for k in range(len(layout.centres)):
            if db.add_image(f"survey_{k:05d}.png", camera_id, rig_id) != k + 1:
                raise RuntimeError("image ids of a new database are not 1..N")  # pycolmap's own numbering
            db.add_keypoints(k + 1, keypoints[k + 1], colmap_coordinates=True)
        for (a, b), m in matches.items():
            db.add_matches(a, b, m, as_inliers=True)
            if fundamental and (a, b) in fundamental:
                tvg = db.handle.read_two_view_geometry(a, b)
                tvg.F = fundamental[(a, b)]
                db.handle.update_two_view_geometry(a, b, tvg)


def survey_keypoints(layout, num_images: int, extra_keypoints: float, width: int, height: int,
                     rng: np.random.Generator) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Keypoints per image of a survey: (true xy (COLMAP coordinates), the point index each one
    sees, -1 for the ``extra_keypoints`` share of keypoints on no point), shuffled."""
    true_xy, seen = [], []
    for k in range(num_images):
        idx, xy = layout.project(k)
        n_extra = int(round(extra_keypoints * len(idx)))
        xy = np.concatenate([xy, rng.uniform((0, 0), (width, height), (n_extra, 2))])
        idx = np.concatenate([idx, np.full(n_extra, -1, np.int64)])
        order = rng.permutation(len(idx))
        true_xy.append(xy[order])
        seen.append(idx[order])
    return true_xy, seen


def make_survey_scene(
    out_dir: str | Path,
    *,
    num_images: int = 25,
    points_per_image: int = 300,
    forward_overlap: float = 0.7,
    side_overlap: float = 0.4,
    sequential: int = 2,
    nearest: int = 6,
    min_pair_matches: int = 15,
    outlier_ratio: float = 0.2,
    noise_px: float = 1.0,
    extra_keypoints: float = 0.1,
    width: int = 1024,
    height: int = 768,
    render_images: bool = True,
    seed: int = 0,
) -> SyntheticScene:
    """Create ``out_dir/database.db`` and ``out_dir/images/`` for an aerial-survey scene
    (see :func:`survey_layout`) with a sequential + k-nearest pair graph (:func:`survey_pairs`).

    A pair is stored when its images share at least ``min_pair_matches`` points (as geometric
    verification would drop the rest): its matches are those true correspondences plus
    ``outlier_ratio`` of wrong ones (distinct keypoints), all stored as two-view-geometry
    inliers of an UNCALIBRATED geometry too, with the pair's true fundamental matrix
    (:meth:`SurveyLayout.relative_geometry`: the camera has no focal prior, so COLMAP's
    verification would store F). Each image has its visible points as keypoints
    (moved by Gaussian noise of ``noise_px`` pixels per axis), ``extra_keypoints`` times as many
    keypoints without a 3D point, in random order. One SIMPLE_RADIAL camera (no distortion,
    focal 1.2 * width). Rendered images keep the true positions.

    Returns:
        A :class:`SyntheticScene` whose ``pairs`` are the stored pairs (image ids).

    Raises:
        ValueError: an argument out of range; the message names it.
    """
    import pycolmap

    _check_noise(outlier_ratio, noise_px)
    if extra_keypoints < 0:
        raise ValueError(f"extra_keypoints must be >= 0, got {extra_keypoints}")
    layout = survey_layout(num_images, width=width, height=height, forward_overlap=forward_overlap,
                           side_overlap=side_overlap, points_per_image=points_per_image, seed=seed)
    database, image_dir = _scene_folder(out_dir)
    rng = np.random.default_rng(seed + 1)

    true_xy, seen = survey_keypoints(layout, num_images, extra_keypoints, width, height, rng)

    gt = pycolmap.Reconstruction()
    f = layout.focal
    gt.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=width, height=height,
                                                   params=[f, width / 2.0, height / 2.0, 0.0], camera_id=1))
    names = [f"survey_{k:05d}.png" for k in range(num_images)]
    for k in range(num_images):
        R = layout.rotations[k]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ layout.centres[k])
        gt.add_image_with_trivial_frame(pycolmap.Image(name=names[k], keypoints=true_xy[k], camera_id=1,
                                                       image_id=k + 1), pose)
    tracks: dict[int, list[tuple[int, int]]] = {}
    for k in range(num_images):
        for kp_index in np.flatnonzero(seen[k] >= 0).tolist():
            tracks.setdefault(int(seen[k][kp_index]), []).append((k + 1, kp_index))
    for p, elements in tracks.items():
        if len(elements) >= 2:
            track = pycolmap.Track()
            for image_id, kp_index in elements:
                track.add_element(image_id, kp_index)
            gt.add_point3D(layout.points[p], track)

    noisy = {}
    for k in range(num_images):
        xy = true_xy[k] + (rng.normal(0.0, noise_px, true_xy[k].shape) if noise_px > 0 else 0.0)
        noisy[k + 1] = np.clip(xy, 0, (width - 1e-3, height - 1e-3))
    stored: dict[tuple[int, int], np.ndarray] = {}
    for a, b in survey_pairs(layout.centres, sequential=sequential, nearest=nearest):
        va, vb = np.flatnonzero(seen[a] >= 0), np.flatnonzero(seen[b] >= 0)
        _, ia, ib = np.intersect1d(seen[a][va], seen[b][vb], assume_unique=True, return_indices=True)
        if len(ia) < max(1, min_pair_matches):
            continue
        m = np.stack([va[ia], vb[ib]], axis=1)
        n_out = int(round(len(m) * outlier_ratio / (1 - outlier_ratio)))
        free_a = np.setdiff1d(np.arange(len(seen[a])), m[:, 0])
        free_b = np.setdiff1d(np.arange(len(seen[b])), m[:, 1])
        n_out = min(n_out, len(free_a), len(free_b))
        if n_out:
            wrong = np.stack([rng.choice(free_a, n_out, replace=False),
                              rng.choice(free_b, n_out, replace=False)], axis=1)
            m = np.concatenate([m, wrong])
        stored[(a + 1, b + 1)] = m[rng.permutation(len(m))]
    fundamental = {(a, b): layout.relative_geometry(a - 1, b - 1)[1] for a, b in stored}
    write_survey_database(database, layout, noisy, stored, fundamental)
    pairs = list(stored)
    gt_kp, ids = _gt_keypoints(gt, {k + 1: len(seen[k]) for k in range(num_images)})
    if render_images:
        pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), gt, str(image_dir))
    log.debug("survey scene: %d images, %d points, %d pairs in %s", num_images, len(tracks), len(pairs),
              database.parent)
    return SyntheticScene(database, image_dir, gt, gt_kp, ids, pairs)
