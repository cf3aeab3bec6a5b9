"""The match check's global estimate of the cameras: pycolmap's global mapper on a temporary
database of the given matches (:func:`global_estimate`), each pair's own relative rotation, and
the placing of an image by its 3D points. Coordinates are COLMAP's inside (rays do not depend on
the convention)."""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..adapters.database import ColmapDatabase, fitted_geometry, is_verified
from ..geometry import fit_fundamental, spread_rows
from ..match_tracks import components, distinct, match_ends, node_offsets, repeated_image
from ..types import Pair, Pose
from .colmap_log import colmap_log_to_file, last_error_line, latest_log, step_seconds
from .mapping import global_options, largest_model, release_freed_heap

if TYPE_CHECKING:
    from ..verification.config import MatchCheckConfig

log = logging.getLogger(__name__)

#: Pixels: RANSAC threshold of each pair's own relative pose (COLMAP's default verification).
PAIR_POSE_MAX_ERROR_PX = 4.0


@dataclass(frozen=True, kw_only=True)
class GlobalEstimate:
    """A global estimate of the cameras (empty when the mapper placed no image).

    Attributes:
        poses: image id -> ``cam_from_world`` (R (3, 3), t (3,)).
        rays: image id -> ``(N, 2)`` normalised coordinates of all its keypoints.
        focal: image id -> mean focal length (pixels) of its estimated camera.
        pair_rotations: pair -> ``R_2from1`` estimated from the pair's matches alone (pairs of
            two registered images with at least ``min_pair_matches`` matches).
        observations: image id -> (keypoint indices int64 ``(K,)``, their 3D points float64
            ``(K, 3)``, their point ids int64 ``(K,)``, their tracks' lengths int64 ``(K,)``)
            of the model's tracks.
        cameras: image id -> its estimated ``pycolmap.Camera``.
        keypoints: image id -> ``(N, 2)`` keypoints in COLMAP's convention.
        seconds: wall time of its parts: "database" (the temporary database), "mapper",
            "pair_rotations".
        mapper_steps: the mapper's own seconds per step, from its log (empty with ``-v``).
        failure: why the mapper gave no model, in COLMAP's words ("" when it gave one).
    """

    poses: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    rays: dict[int, np.ndarray] = field(default_factory=dict)
    focal: dict[int, float] = field(default_factory=dict)
    pair_rotations: dict[Pair, np.ndarray] = field(default_factory=dict)
    observations: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    cameras: dict = field(default_factory=dict)
    keypoints: dict[int, np.ndarray] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    mapper_steps: dict[str, float] = field(default_factory=dict)
    failure: str = ""


def global_estimate(src: ColmapDatabase, matches: Mapping[Pair, np.ndarray], cfg: MatchCheckConfig, *,
                    seed: int = 0, num_threads: int = -1, verbose: bool = False,
                    workdir: Path | None = None) -> GlobalEstimate:
    """Run pycolmap's global mapper on ``matches`` with the cameras of ``src``.

    Args:
        src: the open working database (read only here).
        matches: pair -> int ``(M, 2)`` keypoint indices, the matches to estimate from.
        cfg: the match check's settings (pairs under ``min_pair_matches`` are left out; the
            mapper gets :func:`sampled_tracks`, its positioning ``positioning_tracks_per_image``
            of them, again with every track where that registers fewer images than the sample
            holds; ``pair_rotation_matches`` caps each pair's own rotation's matches).
        seed: the match check's seed (:mod:`colmap_miho.seeds`): the track sample's, the
            mapper's and the pairs' RANSAC.
        num_threads: mapper threads (-1: all cores).
        verbose: COLMAP's log on the terminal instead of the temporary folder's file (a failed
            estimate is the caller's to report).
        workdir: where the temporary folder goes (default ``$TMPDIR``; always removed).

    Returns:
        The :class:`GlobalEstimate`, empty when no model came out.

    Raises:
        RunFailed: the disk of the temporary folder is full.
    """
    import pycolmap

    from ..adapters.staged_write import disk_full_error, is_disk_full, private_tempdir

    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    kp = {im.image_id: src.raw_keypoints(im.image_id)[:, :2].astype(np.float64) for im in src.images()}
    used = {p: np.asarray(m, np.int64) for p, m in matches.items() if len(m) >= cfg.min_pair_matches}
    with private_tempdir("miho-global-", workdir) as folder:
        try:
            tracks = sampled_tracks(used, {i: len(k) for i, k in kp.items()}, cfg.estimate_matches_per_image,
                                    cfg.min_pair_matches, seed)
            written = src.write_scene_copy(folder / "global.db", tracks, _fit_geometry(kp, seed),
                                           matched_keypoints_only=True)
            seconds["database"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            recs, failure, steps = _run_mapper(pycolmap, folder, cfg, seed, num_threads, verbose,
                                               cfg.positioning_tracks_per_image)
            seconds["mapper"] = time.perf_counter() - t0
            if cfg.positioning_tracks_per_image > 0 and _registered(recs) < len({i for p in tracks for i in p}):
                # the positioning from a share of the tracks lost images: every track, the better of the two
                t0 = time.perf_counter()
                again = _run_mapper(pycolmap, folder, cfg, seed, num_threads, verbose, 0, "model_every_track")
                if _registered(again[0]) > _registered(recs):
                    recs, failure, steps = again
                seconds["mapper_every_track"] = time.perf_counter() - t0
        except (OSError, RuntimeError) as exc:
            if is_disk_full(exc):
                raise disk_full_error(folder.parent, "writing the global estimate's temporary database", exc) from None
            raise
    rec = largest_model(recs)
    if rec is None:
        return GlobalEstimate(seconds=seconds, mapper_steps=steps, failure=failure)
    model = _read_model(rec, kp, written)
    del rec, recs
    release_freed_heap()  # the mapper's freed memory, held otherwise through the judging and restoring
    t0 = time.perf_counter()
    cams = model["cameras"]
    sample = evenly_spaced(used, cfg.pair_rotation_matches)
    stored = {p: src.verified_model(*p) for p in sample if p[0] in cams and p[1] in cams}
    rotations = _pair_rotations(pycolmap, sample, stored, kp, cams, seed, num_threads)
    seconds["pair_rotations"] = time.perf_counter() - t0
    return GlobalEstimate(**model, seconds=seconds, mapper_steps=steps, keypoints=kp, pair_rotations=rotations)


def sampled_tracks(matches: Mapping[Pair, np.ndarray], num_keypoints: Mapping[int, int], per_image: int,
                   min_pair_matches: int, seed: int) -> dict[Pair, np.ndarray]:
    """The matches the global mapper is given: a seeded sample of whole tracks, each kept with
    probability ``per_image`` over the match ends per image; all matches with ``per_image`` 0,
    when there are no more than that per image, or when the consistent tracks hold fewer.

    Tracks holding two keypoints of one image are left out (repeated structure chains copies
    together; the mapper then turns groups of images), and thinning whole tracks rather than
    each pair keeps the tracks the mapper sees unbroken. Pairs left with fewer than
    ``min_pair_matches`` matches are dropped.
    """
    total = sum(len(m) for m in matches.values())
    num_images = len({i for p in matches for i in p})
    share = per_image * num_images / (2 * total) if total else 1.0
    if per_image <= 0 or share >= 1.0:
        return dict(matches)
    offset, n = node_offsets(num_keypoints)
    pairs = sorted(matches)
    a, b = match_ends(offset, ((i, j, matches[(i, j)]) for i, j in pairs))
    count, track = components(a, b, n)
    nodes = distinct(np.concatenate([a, b]), n)
    image_of = np.searchsorted(np.asarray(list(offset.values()), np.int64), nodes, side="right") - 1
    consistent = ~repeated_image(track[nodes], image_of, count)
    if 2 * int(consistent[track[a]].sum()) < per_image * num_images:
        return dict(matches)  # too few consistent tracks to sample from: every match, as without a sample
    keep = (np.random.default_rng(seed).random(count) < share) & consistent
    out = {}
    for i, j in pairs:
        m = matches[(i, j)][keep[track[offset[i] + matches[(i, j)][:, 0]]]]
        if len(m) >= min_pair_matches:
            out[(i, j)] = m
    return out


def _fit_geometry(kp: Mapping[int, np.ndarray], seed: int):
    """``fit(i, j, m)``: a two-view geometry holding F fitted to the pair's matches (None: no fit)."""
    def fit(i: int, j: int, m: np.ndarray):
        F = fit_fundamental(kp[i][m[:, 0]], kp[j][m[:, 1]], np.random.default_rng([seed, i, j]))
        return None if F is None else fitted_geometry(F, None)

    return fit


def _registered(models: dict) -> int:
    """Images registered in the largest of ``models`` (0 without models)."""
    rec = largest_model(models)
    return 0 if rec is None else int(rec.num_reg_images())


def _run_mapper(pc, folder: Path, cfg: MatchCheckConfig, seed: int, num_threads: int, verbose: bool,
                tracks_per_image: int, name: str = "model") -> tuple[dict, str, dict[str, float]]:
    """``pycolmap.global_mapping`` on ``folder``'s ``global.db`` into ``folder/name``, its
    positioning from the longest tracks until each image has ``tracks_per_image`` (0: every
    track); returns (its models, why it gave none in COLMAP's words ("" when it gave some), the
    seconds of its steps from its log)."""
    from ..adapters.staged_write import is_disk_full

    opts = global_options(seed=seed, num_threads=num_threads, min_num_matches=cfg.min_pair_matches)
    opts.mapper.ba_num_iterations = int(cfg.ba_iterations)
    opts.mapper.skip_retriangulation = not cfg.retriangulate
    if tracks_per_image > 0:
        opts.mapper.track_required_tracks_per_view = int(tracks_per_image)
    if cfg.ba_function_tolerance > 0:
        opts.mapper.bundle_adjustment.ceres.solver_options.function_tolerance = float(cfg.ba_function_tolerance)
    out = folder / name
    out.mkdir()
    failure = ""
    with colmap_log_to_file(out, verbose=verbose, errors_to_terminal=False, replay=True) as prefix:
        try:
            recs = pc.global_mapping(str(folder / "global.db"), str(folder), str(out), opts)
        except RuntimeError as exc:  # COLMAP's own check failed: no estimate, the run goes on
            if is_disk_full(exc):
                raise
            recs, failure = {}, " ".join(str(exc).split())
    log_file = latest_log(prefix)
    if not recs and not failure:
        failure = last_error_line(log_file)
    return recs, failure, step_seconds(log_file)


def _read_model(rec, kp: Mapping[int, np.ndarray], written: Mapping[int, np.ndarray] | None = None) -> dict:
    """The :class:`GlobalEstimate` fields ``poses``, ``rays``, ``focal``, ``cameras`` and
    ``observations`` of the model ``rec`` (its registered images); ``written``: image id -> the
    keypoint indices the mapper's keypoints stand for (None: the same indices)."""
    poses, rays, focal, cams = {}, {}, {}, {}
    for image_id, im in rec.images.items():
        if not im.has_pose:
            continue
        p = im.cam_from_world()
        cam = rec.cameras[im.camera_id]
        i = int(image_id)
        poses[i] = (np.asarray(p.rotation.matrix(), np.float64), np.asarray(p.translation, np.float64))
        rays[i] = np.asarray(cam.cam_from_img(kp[i]), np.float64).reshape(-1, 2)
        focal[i] = float(cam.mean_focal_length())
        cams[i] = cam
    obs: dict[int, tuple[list, list, list, list]] = {i: ([], [], [], []) for i in poses}
    for point_id, p3 in rec.points3D.items():
        elements = p3.track.elements
        for el in elements:
            if int(el.image_id) in obs:
                row = obs[int(el.image_id)]
                row[0].append(int(el.point2D_idx))
                row[1].append(p3.xyz)
                row[2].append(int(point_id))
                row[3].append(len(elements))
    observations = {i: (np.asarray(a, np.int64) if written is None else written[i][np.asarray(a, np.int64)],
                        np.asarray(b, np.float64).reshape(-1, 3), np.asarray(c, np.int64),
                        np.asarray(d, np.int64)) for i, (a, b, c, d) in obs.items()}
    return {"poses": poses, "rays": rays, "focal": focal, "cameras": cams, "observations": observations}


@dataclass(frozen=True, kw_only=True)
class GlobalEstimator:
    """The match check's estimator (:class:`colmap_miho.verification.match_check.Estimator`):
    :func:`global_estimate` on the open working database ``src`` with the check's ``config``,
    and :func:`place_by_points` for the images the check did not trust (at
    ``config.max_threshold_px``, with ``config.min_placed_inliers`` inliers)."""

    src: ColmapDatabase
    config: MatchCheckConfig
    seed: int = 0
    num_threads: int = -1
    verbose: bool = False
    workdir: Path | None = None

    def estimate(self, matches: Mapping[Pair, np.ndarray]) -> GlobalEstimate:
        return global_estimate(self.src, matches, self.config, seed=self.seed, num_threads=self.num_threads,
                               verbose=self.verbose, workdir=self.workdir)

    def place(self, estimate: GlobalEstimate, image_id: int, matches: Mapping[Pair, np.ndarray],
              trusted: frozenset[int], min_inliers: int | None = None) -> Pose | None:
        cfg = self.config
        return place_by_points(estimate, image_id, matches, trusted, max_error_px=cfg.max_threshold_px,
                               min_inliers=cfg.min_placed_inliers if min_inliers is None else min_inliers,
                               seed=self.seed)


def place_by_points(est: GlobalEstimate, image_id: int, matches: Mapping[Pair, np.ndarray], trusted, *,
                    max_error_px: float, min_inliers: int, seed: int = 0) -> Pose | None:
    """A new ``cam_from_world`` of placed image ``image_id`` from the estimate's 3D points that
    its keypoints match through the ``trusted`` images (absolute pose, LO-RANSAC at
    ``max_error_px`` and refinement, as incremental mapping registers an image); None with
    fewer than ``min_inliers`` inliers."""
    import pycolmap

    k = int(image_id)
    if k not in est.cameras:
        return None
    p2, p3 = [], []
    for (i, j), m in matches.items():
        if k not in (i, j):
            continue
        other, mine, theirs = (j, m[:, 0], m[:, 1]) if i == k else (i, m[:, 1], m[:, 0])
        if other not in trusted or other not in est.observations:
            continue
        idx, xyz = est.observations[other][:2]
        order = np.argsort(idx)
        pos = np.searchsorted(idx[order], theirs)
        pos = np.minimum(pos, max(len(idx) - 1, 0))
        hit = (idx[order][pos] == theirs) if len(idx) else np.zeros(len(theirs), bool)
        p2.append(est.keypoints[k][mine[hit]])
        p3.append(xyz[order][pos[hit]])
    if not p2 or sum(len(a) for a in p2) < min_inliers:
        return None
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = float(max_error_px)
    opts.ransac.random_seed = int(seed)
    out = pycolmap.estimate_and_refine_absolute_pose(np.concatenate(p2), np.concatenate(p3), est.cameras[k], opts)
    if out is None or int(out["num_inliers"]) < min_inliers:
        return None
    pose = out["cam_from_world"]
    return np.asarray(pose.rotation.matrix(), np.float64), np.asarray(pose.translation, np.float64)


def evenly_spaced(matches: Mapping[Pair, np.ndarray], most: int) -> dict[Pair, np.ndarray]:
    """At most ``most`` of each pair's matches, evenly spaced over them in their order (all of
    them with ``most`` 0)."""
    if most <= 0:
        return dict(matches)
    return {p: m[spread_rows(len(m), most)] for p, m in matches.items()}


def _pair_rotations(pc, matches: Mapping[Pair, np.ndarray], stored: Mapping[Pair, Any],
                    kp: Mapping[int, np.ndarray], cams: Mapping, seed: int, num_threads: int = 1
                    ) -> dict[Pair, np.ndarray]:
    """Each pair's own ``R_2from1`` from its matches (pairs of two registered images whose
    relative pose could be found): the pose of the pair's stored CALIBRATED model (``stored``:
    pair -> ``pycolmap.TwoViewGeometry`` or None) over the matches, whose inliers they are,
    else a RANSAC estimate from the matches alone. Only an essential matrix is reused: an
    UNCALIBRATED F fitted without the focal length turns near-planar pairs by degrees, and a
    PLANAR H decomposes two ways. On ``num_threads`` threads (-1: all cores; pycolmap releases
    the GIL, and each pair's RANSAC is seeded alone, so the result does not depend on the
    threads)."""
    calibrated = int(pc.TwoViewGeometryConfiguration.CALIBRATED)
    opts = pc.TwoViewGeometryOptions()
    opts.compute_relative_pose = True
    opts.ransac.max_error = PAIR_POSE_MAX_ERROR_PX
    opts.ransac.random_seed = int(seed)
    todo = [(p, m) for p, m in sorted(matches.items()) if p[0] in cams and p[1] in cams]

    def rotation(item: tuple[Pair, np.ndarray]) -> np.ndarray | None:
        (i, j), m = item
        m = np.ascontiguousarray(m, np.uint32)
        tvg = stored.get((i, j))
        if tvg is not None and int(tvg.config) == calibrated:
            tvg.inlier_matches = m
            with contextlib.suppress(ValueError):  # COLMAP's check: a model without its matrix
                if pc.estimate_two_view_geometry_pose(cams[i], kp[i], cams[j], kp[j], tvg):
                    return np.asarray(tvg.cam2_from_cam1.rotation.matrix(), np.float64)
        tvg = pc.estimate_two_view_geometry(cams[i], kp[i], cams[j], kp[j], m, opts)
        pose = tvg.cam2_from_cam1
        return np.asarray(pose.rotation.matrix(), np.float64) if is_verified(tvg) and pose is not None else None

    threads = max(1, min(len(todo), (os.cpu_count() or 1) if num_threads < 0 else int(num_threads)))
    with ThreadPoolExecutor(threads) as pool:
        found = list(pool.map(rotation, todo))
    return {p: R for (p, _), R in zip(todo, found, strict=True) if R is not None}
