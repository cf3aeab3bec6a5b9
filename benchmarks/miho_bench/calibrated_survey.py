"""A realistic aerial survey: calibrated cameras, COLMAP's stored two-view geometry, thousands of
matches per pair with wrong and repeated-structure ones, and the pair graphs users have.

:func:`make_survey_scene` (``synthetic.py``) holds about 1,100 match ends per image; a real
8192-SIFT scene holds 8,000-28,000. :func:`make_calibrated_survey` builds the survey of
:func:`~miho_bench.synthetic.survey_layout` (80% forward / 60% side overlap by default, so a
point is seen by about 12 images) the way COLMAP's matcher would store it:

- one SIMPLE_PINHOLE camera with a focal prior (``has_prior_focal_length``), so every verified
  pair is CALIBRATED with its true ``E`` and ``F`` (:meth:`SurveyLayout.relative_geometry`);
- the ``matches`` table holds the raw matches: ``recall`` of the true correspondences, a share
  ``repeated_ratio`` of them replaced by a wrong keypoint lying within ``repeated_px`` of the
  true epipolar line (a facade's next window: it passes any two-view check), and
  ``random_ratio`` random wrong ones between keypoints left unmatched;
- ``two_view_geometries.inlier_matches`` holds those of them whose Sampson distance to the true
  ``F`` (on the stored, noisy keypoints) is under ``verify_px`` (COLMAP's ``max_error``, 4 px);
  a pair with fewer than ``min_inliers`` is stored with its raw matches only, as COLMAP does;
- pair graphs (``graph``): "exhaustive" (every pair of images sharing points: exhaustive
  matching's verified pairs; pairs that share nothing would fail verification and are not
  generated), "sequential" (each image with its next ``neighbours`` in capture order, plus loop
  closures: every ``loop_period``-th image with the ``loop_images`` images it overlaps most
  outside that window, as COLMAP's sequential matcher with loop detection), "retrieval" (each
  image with the ``neighbours`` images it overlaps most: an image-retrieval top-k).

Correct matches are the planted true correspondences (two observations of one 3D point:
:meth:`SyntheticScene.is_true_match`); everything else is wrong. Images are rendered by
``pycolmap.synthesize_images`` with small patches (``patch_radius``) so that neighbouring points'
patches rarely overlap.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from colmap_miho.adapters.database import ColmapDatabase

from .synthetic import SurveyLayout, SyntheticScene, _gt_keypoints, _scene_folder, survey_keypoints, survey_layout

log = logging.getLogger(__name__)

GRAPHS = ("exhaustive", "sequential", "retrieval")


@dataclass
class CalibratedSurvey(SyntheticScene):
    """A :class:`SyntheticScene` with the survey's layout and pair graph.

    Attributes:
        layout: the cameras and terrain points.
        graph: "exhaustive", "sequential" or "retrieval".
        candidate_pairs: the pairs the graph chose (0-based image indices, i < j), verified or not.
        loop_pairs: the sequential graph's loop closures among them (0-based).
    """

    layout: SurveyLayout | None = None
    graph: str = ""
    candidate_pairs: list[tuple[int, int]] | None = None
    loop_pairs: list[tuple[int, int]] | None = None


def overlap_counts(layout: SurveyLayout, seen: list[np.ndarray]) -> np.ndarray:
    """int64 (N, N): points seen by both images (0 on the diagonal); ``seen[k]`` holds the point
    index of every keypoint of image k (-1 for none)."""
    from scipy import sparse

    rows = np.concatenate([np.full(int((s >= 0).sum()), k) for k, s in enumerate(seen)])
    cols = np.concatenate([s[s >= 0] for s in seen])
    a = sparse.csr_matrix((np.ones(len(rows), np.int64), (rows, cols)), shape=(len(seen), len(layout.points)))
    c = (a @ a.T).toarray().astype(np.int64)
    np.fill_diagonal(c, 0)
    return c


def graph_pairs(overlap: np.ndarray, graph: str, *, neighbours: int = 10, loop_period: int = 10,
                loop_images: int = 5, min_shared: int = 15) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """The candidate pairs of a pair graph over images in capture order, and the loop closures
    among them (sequential only), both as sorted 0-based (i, j), i < j. Pairs of images sharing
    fewer than ``min_shared`` points are left out (their verification would fail)."""
    if graph not in GRAPHS:
        raise ValueError(f"graph must be one of {', '.join(GRAPHS)}, got {graph!r}")
    n = len(overlap)
    pairs: set[tuple[int, int]] = set()
    loops: set[tuple[int, int]] = set()
    if graph == "exhaustive":
        i, j = np.nonzero(np.triu(overlap >= min_shared, 1))
        pairs.update(zip(i.tolist(), j.tolist(), strict=True))
    elif graph == "sequential":
        pairs.update((i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + neighbours)))
        for i in range(0, n, max(1, loop_period)):
            score = overlap[i].astype(float)
            score[max(0, i - neighbours):i + neighbours + 1] = -1  # outside the sequential window
            for j in np.argsort(-score, kind="stable")[:loop_images]:
                if score[j] >= min_shared:
                    loops.add((min(i, int(j)), max(i, int(j))))
        pairs |= loops
    else:
        for i in range(n):
            score = overlap[i].astype(float)
            score[i] = -1
            pairs.update((min(i, int(j)), max(i, int(j))) for j in np.argsort(-score, kind="stable")[:neighbours])
    pairs = {p for p in pairs if overlap[p] >= min_shared}
    return sorted(pairs), sorted(loops)


def sampson_px(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """float64 (M,) Sampson distance (pixels) of correspondences ``xa`` -> ``xb`` (M, 2) under
    ``F`` (``x_b^T F x_a = 0``)."""
    ha = np.column_stack([xa, np.ones(len(xa))])
    hb = np.column_stack([xb, np.ones(len(xb))])
    fa, fb = ha @ F.T, hb @ F
    num = np.einsum("ij,ij->i", hb, fa)
    den = fa[:, 0] ** 2 + fa[:, 1] ** 2 + fb[:, 0] ** 2 + fb[:, 1] ** 2
    return np.abs(num) / np.sqrt(np.maximum(den, 1e-300))


def line_distance_px(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """float64 (K, L): distance (pixels) of each point ``xb`` (L, 2) of image b to the epipolar
    line of each point ``xa`` (K, 2) of image a."""
    la = np.column_stack([xa, np.ones(len(xa))]) @ F.T  # (K, 3)
    d = la[:, :2] @ xb.T + la[:, 2:3]
    return np.abs(d) / np.linalg.norm(la[:, :2], axis=1, keepdims=True)


def pair_matches(rng: np.random.Generator, F: np.ndarray, seen_a: np.ndarray, seen_b: np.ndarray,
                 true_a: np.ndarray, true_b: np.ndarray, *, recall: float, repeated_ratio: float,
                 repeated_px: float, random_ratio: float) -> np.ndarray:
    """One pair's raw matches, int64 (M, 2) keypoint indices (a, b), in random order: true
    correspondences, repeated-structure ones and random wrong ones (module docstring); the
    keypoints of b are used at most once."""
    va, vb = np.flatnonzero(seen_a >= 0), np.flatnonzero(seen_b >= 0)
    _, ia, ib = np.intersect1d(seen_a[va], seen_b[vb], assume_unique=True, return_indices=True)
    m = np.stack([va[ia], vb[ib]], axis=1)
    m = m[rng.random(len(m)) < recall]
    used_b = np.zeros(len(seen_b), bool)
    used_b[m[:, 1]] = True
    n_rep = int(round(repeated_ratio * len(m)))
    if n_rep:  # replace the partner in b by an unused keypoint near the epipolar line, 15-150 px away
        rows = rng.choice(len(m), n_rep, replace=False)
        free = np.flatnonzero(~used_b)
        d_line = line_distance_px(F, true_a[m[rows, 0]], true_b[free])
        d_true = np.linalg.norm(true_b[free][None, :, :] - true_b[m[rows, 1]][:, None, :], axis=2)
        ok = (d_line < repeated_px) & (d_true > 15) & (d_true < 150)
        pick = np.where(ok, rng.random(ok.shape), -1.0).argmax(axis=1)
        has = ok[np.arange(len(rows)), pick]
        rows, cand = rows[has], free[pick[has]]
        cand, first = np.unique(cand, return_index=True)  # one use per keypoint of b
        rows = rows[first]
        used_b[m[rows, 1]] = False
        m[rows, 1] = cand
        used_b[cand] = True
    n_rand = int(round(random_ratio * len(m)))
    free_a = np.setdiff1d(np.arange(len(seen_a)), m[:, 0])
    free_b = np.flatnonzero(~used_b)
    n_rand = min(n_rand, len(free_a), len(free_b))
    if n_rand:
        wrong = np.stack([rng.choice(free_a, n_rand, replace=False), rng.choice(free_b, n_rand, replace=False)], 1)
        m = np.concatenate([m, wrong])
    return m[rng.permutation(len(m))]


def make_calibrated_survey(
    out_dir: str | Path,
    *,
    num_images: int = 100,
    graph: str = "sequential",
    points_per_image: int = 2500,
    forward_overlap: float = 0.8,
    side_overlap: float = 0.6,
    neighbours: int = 10,
    loop_period: int = 10,
    loop_images: int = 5,
    recall: float = 0.8,
    repeated_ratio: float = 0.05,
    repeated_px: float = 1.5,
    random_ratio: float = 0.25,
    verify_px: float = 4.0,
    min_inliers: int = 15,
    noise_px: float = 0.7,
    extra_keypoints: float = 0.5,
    width: int = 1024,
    height: int = 768,
    patch_radius: int = 5,
    render_images: bool = True,
    seed: int = 0,
) -> CalibratedSurvey:
    """Create ``out_dir/database.db`` and ``out_dir/images/`` for a calibrated survey (module
    docstring). ``extra_keypoints``: keypoints without a 3D point per visible point (SIFT finds
    many that match nothing); ``noise_px``: Gaussian noise per axis of the stored keypoints
    (images keep the true positions).

    Returns:
        A :class:`CalibratedSurvey`; ``pairs`` are the verified pairs (image ids, i < j).

    Raises:
        ValueError: an argument out of range; the message names it.
    """
    import pycolmap

    for name, v in (("recall", recall), ("repeated_ratio", repeated_ratio), ("random_ratio", random_ratio)):
        if not 0 <= v <= 1:
            raise ValueError(f"{name} must be in [0, 1], got {v}")
    if noise_px < 0 or extra_keypoints < 0:
        raise ValueError(f"noise_px and extra_keypoints must be >= 0, got {noise_px}, {extra_keypoints}")
    if neighbours < 1:
        raise ValueError(f"neighbours must be >= 1, got {neighbours}")
    layout = survey_layout(num_images, width=width, height=height, forward_overlap=forward_overlap,
                           side_overlap=side_overlap, points_per_image=points_per_image, seed=seed)
    database, image_dir = _scene_folder(out_dir)
    rng = np.random.default_rng(seed + 1)

    true_xy, seen = survey_keypoints(layout, num_images, extra_keypoints, width, height, rng)
    noisy = [np.clip(xy + rng.normal(0.0, noise_px, xy.shape), 0, (width - 1e-3, height - 1e-3)) for xy in true_xy]

    overlap = overlap_counts(layout, seen)
    candidates, loops = graph_pairs(overlap, graph, neighbours=neighbours, loop_period=loop_period,
                                    loop_images=loop_images, min_shared=min_inliers)
    raw: dict[tuple[int, int], np.ndarray] = {}
    geometry: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for a, b in candidates:
        E, F = layout.relative_geometry(a, b)
        m = pair_matches(rng, F, seen[a], seen[b], true_xy[a], true_xy[b], recall=recall,
                         repeated_ratio=repeated_ratio, repeated_px=repeated_px, random_ratio=random_ratio)
        raw[(a + 1, b + 1)] = m
        inl = m[sampson_px(F, noisy[a][m[:, 0]], noisy[b][m[:, 1]]) < verify_px]
        if len(inl) >= min_inliers:
            geometry[(a + 1, b + 1)] = (E, F, inl)

    with ColmapDatabase.create(database) as db, db.transaction():
        h = db.handle
        cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=width, height=height,
                              params=[layout.focal, width / 2.0, height / 2.0])
        cam.has_prior_focal_length = True
        camera_id = h.write_camera(cam)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id))
        rig_id = h.write_rig(rig)
        for k in range(num_images):
            if db.add_image(f"survey_{k:05d}.png", camera_id, rig_id) != k + 1:
                raise RuntimeError("image ids of a new database are not 1..N")
            db.add_keypoints(k + 1, noisy[k], colmap_coordinates=True)
        for (a, b), m in raw.items():
            h.write_matches(a, b, np.ascontiguousarray(m, np.uint32))
            if (a, b) in geometry:
                E, F, inl = geometry[(a, b)]
                tvg = pycolmap.TwoViewGeometry()
                tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                tvg.E, tvg.F = E, F
                tvg.inlier_matches = np.ascontiguousarray(inl, np.uint32)
                h.write_two_view_geometry(a, b, tvg)

    gt = _gt_reconstruction(pycolmap, layout, true_xy, seen)
    gt_kp, ids = _gt_keypoints(gt, {k + 1: len(seen[k]) for k in range(num_images)})
    if render_images:
        opts = pycolmap.SyntheticImageOptions()
        opts.feature_patch_radius = int(patch_radius)
        pycolmap.synthesize_images(opts, gt, str(image_dir))
    log.debug("calibrated survey: %d images, %s graph, %d verified pairs in %s", num_images, graph,
              len(geometry), database.parent)
    return CalibratedSurvey(database, image_dir, gt, gt_kp, ids, sorted(geometry), layout=layout, graph=graph,
                            candidate_pairs=candidates, loop_pairs=loops)


def _gt_reconstruction(pycolmap, layout: SurveyLayout, true_xy: list[np.ndarray], seen: list[np.ndarray]):
    """The ground-truth ``pycolmap.Reconstruction``: true poses, noise-free keypoints, a 3D point
    for every terrain point seen by two or more images."""
    gt = pycolmap.Reconstruction()
    w, h = layout.width, layout.height
    gt.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h,
                                                   params=[layout.focal, w / 2.0, h / 2.0], camera_id=1))
    for k in range(len(seen)):
        R = layout.rotations[k]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ layout.centres[k])
        gt.add_image_with_trivial_frame(pycolmap.Image(name=f"survey_{k:05d}.png", keypoints=true_xy[k],
                                                       camera_id=1, image_id=k + 1), pose)
    image_of = np.concatenate([np.full(int((s >= 0).sum()), k + 1) for k, s in enumerate(seen)])
    kp_of = np.concatenate([np.flatnonzero(s >= 0) for s in seen])
    point_of = np.concatenate([s[s >= 0] for s in seen])
    order = np.argsort(point_of, kind="stable")
    point_of, image_of, kp_of = point_of[order], image_of[order], kp_of[order]
    starts = np.flatnonzero(np.diff(np.concatenate([[-1], point_of])))
    ends = np.append(starts[1:], len(point_of))
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        if e - s >= 2:
            track = pycolmap.Track()
            for image_id, kp in zip(image_of[s:e].tolist(), kp_of[s:e].tolist(), strict=True):
                track.add_element(image_id, kp)
            gt.add_point3D(layout.points[point_of[s]], track)
    return gt
