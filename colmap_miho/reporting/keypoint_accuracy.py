"""Keypoint accuracy under ground-truth cameras, the measure refinement is judged by.

- **Epipolar distance** of every stored inlier match between two GT images: the symmetric
  point-to-epipolar-line distance (px) under the GT ``F_2from1``.
- **GT track residuals**: the tracks of the stored inliers (:mod:`colmap_miho.match_tracks`);
  one holding two keypoints of one image is *conflicting*, counted apart. Each other track seen
  by at least :data:`MIN_TRACK_VIEWS` GT images is triangulated with the GT cameras (DLT, then
  Gauss-Newton on the pixel error); tracks whose largest residual is at most
  :data:`TRACK_THRESHOLD_PX` are *measured*, the others are *wrong tracks*. A track's own
  triangulation absorbs 3 degrees of freedom: with Gaussian noise ``sigma`` px per axis over
  ``n`` views the mean squared residual is ``2 sigma^2 (1 - 3 / (2 n))``.

Pure numpy/scipy. Pixels: integer = pixel centre, for the keypoints and the intrinsics ``K``.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping
from dataclasses import asdict, dataclass

import numpy as np

from ..geometry import fundamental_from_poses, symmetric_epipolar_distance
from ..match_tracks import build_tracks, match_ends, node_offsets, repeated_image
from .track_geometry import GAUSS_NEWTON_STEPS, triangulate_tracks

EPIPOLAR_THRESHOLD_PX = 2.0
"""A stored inlier match farther than this (px, symmetric) from its GT epipolar line is counted
in ``epipolar_share_above``."""

TRACK_THRESHOLD_PX = 4.0
"""A track whose largest GT reprojection residual exceeds this (px) is a *wrong track*: it joins
keypoints of different 3D points, so its residuals measure matching errors, not localisation."""

MIN_TRACK_VIEWS = 3
"""Tracks seen by fewer GT images are not measured (two views leave the residual nearly free)."""



@dataclass(frozen=True, kw_only=True)
class KeypointAccuracy:
    """Keypoint accuracy of one database under GT geometry (see the module docstring).

    Attributes:
        num_matches: stored inlier matches between two GT images (epipolar distances measured).
        epipolar_median_px: median symmetric epipolar distance of those matches (px).
        epipolar_share_above: share of them farther than ``epipolar_threshold_px``.
        num_tracks: tracks seen by >= ``min_track_views`` GT images (conflicting ones included).
        num_conflicting_tracks: of those, tracks holding two keypoints of one image (any image);
            not measured.
        num_measured_tracks: tracks whose largest residual is <= ``track_threshold_px``.
        num_measured_observations: their GT observations.
        residual_median_px / residual_mean_px / residual_p90_px: reprojection residuals of the
            measured observations (px).
        num_wrong_tracks: non-conflicting tracks above ``track_threshold_px`` (or not
            triangulable).
        wrong_track_share: ``num_wrong_tracks / (num_measured_tracks + num_wrong_tracks)``.
        epipolar_threshold_px, track_threshold_px, min_track_views: the thresholds used.
    NaN where nothing was measured.
    """

    num_matches: int
    epipolar_median_px: float
    epipolar_share_above: float
    num_tracks: int
    num_conflicting_tracks: int
    num_measured_tracks: int
    num_measured_observations: int
    residual_median_px: float
    residual_mean_px: float
    residual_p90_px: float
    num_wrong_tracks: int
    wrong_track_share: float
    epipolar_threshold_px: float
    track_threshold_px: float
    min_track_views: int

    def to_dict(self) -> dict:
        """Plain dict with the attribute names as keys (stable), NaN as None (JSON-ready)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}


# --------------------------------------------------------------------------- cameras
def camera_krt(cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, R, t) float64 from an object with ``K, R, t`` attributes or a 3-tuple."""
    if hasattr(cam, "K") and hasattr(cam, "R") and hasattr(cam, "t"):
        K, R, t = cam.K, cam.R, cam.t
    else:
        K, R, t = cam
    K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
    if K.shape != (3, 3) or R.shape != (3, 3) or t.reshape(-1).shape != (3,):
        raise ValueError(f"a camera needs K (3, 3), R (3, 3), t (3,); got {K.shape}, {R.shape}, {t.shape}")
    return K, R, t.reshape(3)


# --------------------------------------------------------------------------- the measure
def keypoint_accuracy(
    cameras: Mapping[Hashable, object],
    keypoints: Mapping[Hashable, np.ndarray],
    matches: Mapping[tuple[Hashable, Hashable], np.ndarray],
    *,
    epipolar_threshold_px: float = EPIPOLAR_THRESHOLD_PX,
    track_threshold_px: float = TRACK_THRESHOLD_PX,
    min_track_views: int = MIN_TRACK_VIEWS,
    gauss_newton_steps: int = GAUSS_NEWTON_STEPS,
) -> KeypointAccuracy:
    """Epipolar distances and GT track residuals of stored inlier matches (see module docstring).

    Args:
        cameras: GT camera per image key: a :class:`~colmap_miho.reporting.gt_model.CameraPose`
            (or any object with ``K`` (3, 3), ``R`` (3, 3), ``t`` (3,)) or a ``(K, R, t)``
            tuple; world-to-camera, pixel-centre intrinsics. Images without a camera take part
            in the tracks' connectivity but are not measured.
        keypoints: (N_i, 2) float pixel positions per image key (integer = pixel centre).
        matches: (M, 2) int keypoint indices per image pair ``(key_a, key_b)``: column 0 into
            ``keypoints[key_a]``, column 1 into ``keypoints[key_b]``.
        epipolar_threshold_px, track_threshold_px, min_track_views: see the module constants.
        gauss_newton_steps: refinement steps after the DLT.

    Returns:
        :class:`KeypointAccuracy`.

    Raises:
        ValueError: a bad threshold, a pair naming an image without keypoints, or a match index
            out of range (the message names the pair).
    """
    if not (epipolar_threshold_px > 0 and track_threshold_px > 0):
        raise ValueError(f"thresholds must be > 0, got epipolar_threshold_px={epipolar_threshold_px}, "
                         f"track_threshold_px={track_threshold_px}")
    if int(min_track_views) < 2:
        raise ValueError(f"min_track_views must be >= 2, got {min_track_views}")
    if int(gauss_newton_steps) < 0:
        raise ValueError(f"gauss_newton_steps must be >= 0, got {gauss_newton_steps}")
    min_track_views = int(min_track_views)
    keys = list(keypoints)
    kps = [np.asarray(keypoints[k], dtype=np.float64).reshape(-1, 2) for k in keys]
    cams = {k: camera_krt(c) for k, c in cameras.items()}
    e, track_matches = _epipolar_distances(keys, kps, cams, matches)
    nan = float("nan")
    tracks = _classify_tracks(keys, kps, cams, track_matches, min_track_views)
    candidate, conflicting = tracks.candidate, tracks.conflicting
    Kp, Rp, tp, xy, valid = _padded_observations(keys, kps, cams, tracks)
    T = len(valid)
    _, res = triangulate_tracks(Kp, Rp, tp, xy, valid, gauss_newton_steps=int(gauss_newton_steps))
    worst = np.where(valid, res, 0.0).max(axis=1) if T else np.zeros(0)
    good = worst <= track_threshold_px
    r = res[good][valid[good]]
    n_good, n_wrong = int(good.sum()), int(T - good.sum())
    return KeypointAccuracy(
        num_matches=int(e.size),
        epipolar_median_px=float(np.median(e)) if e.size else nan,
        epipolar_share_above=float(np.mean(e > epipolar_threshold_px)) if e.size else nan,
        num_tracks=int(candidate.sum()),
        num_conflicting_tracks=int(conflicting.sum()),
        num_measured_tracks=n_good,
        num_measured_observations=int(r.size),
        residual_median_px=float(np.median(r)) if r.size else nan,
        residual_mean_px=float(np.mean(r)) if r.size else nan,
        residual_p90_px=float(np.quantile(r, 0.9)) if r.size else nan,
        num_wrong_tracks=n_wrong,
        wrong_track_share=float(n_wrong / T) if T else nan,
        epipolar_threshold_px=float(epipolar_threshold_px),
        track_threshold_px=float(track_threshold_px),
        min_track_views=min_track_views,
    )


def _epipolar_distances(keys: list, kps: list[np.ndarray], cams: dict,
                        matches: Mapping[tuple[Hashable, Hashable], np.ndarray]
                        ) -> tuple[np.ndarray, list[tuple[int, int, np.ndarray]]]:
    """Symmetric GT epipolar distances (px) of the matches between two GT images, and every
    pair's matches as ``(image index a, image index b, (M, 2) int64 indices)`` for the tracks.

    Raises:
        ValueError: a pair naming an image without keypoints, or a match index out of range.
    """
    index = {k: i for i, k in enumerate(keys)}
    epi = []
    track_matches = []
    for (a, b), idx in matches.items():
        if a not in index or b not in index:
            raise ValueError(f"pair ({a!r}, {b!r}): no keypoints for {a if a not in index else b!r}")
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, 2)
        if len(idx) == 0:
            continue
        ia, ib = index[a], index[b]
        if idx.min() < 0 or idx[:, 0].max() >= len(kps[ia]) or idx[:, 1].max() >= len(kps[ib]):
            raise ValueError(f"pair ({a!r}, {b!r}): match index out of range "
                             f"({len(kps[ia])} and {len(kps[ib])} keypoints)")
        track_matches.append((ia, ib, idx))
        if a in cams and b in cams:
            F = fundamental_from_poses(*cams[a], *cams[b])
            epi.append(symmetric_epipolar_distance(F, kps[ia][idx[:, 0]], kps[ib][idx[:, 1]]))
    return (np.concatenate(epi) if epi else np.zeros(0)), track_matches


@dataclass(frozen=True)
class _Tracks:
    """The tracks of all matches: per observation its node, image index, GT flag and track
    label; per track whether it is a candidate (seen by ``min_track_views`` GT images), a
    conflicting one (two keypoints of one image) and so measured (candidate, not conflicting)."""

    nodes: np.ndarray
    img: np.ndarray
    gt_obs: np.ndarray
    lab: np.ndarray
    candidate: np.ndarray
    conflicting: np.ndarray
    measured: np.ndarray


def _classify_tracks(keys: list, kps: list[np.ndarray], cams: dict,
                     track_matches: list[tuple[int, int, np.ndarray]], min_track_views: int) -> _Tracks:
    """The tracks of ``track_matches`` and their classes (see :class:`_Tracks`)."""
    offset, total = node_offsets({k: len(x) for k, x in enumerate(kps)})
    nodes, lab = build_tracks(*match_ends(offset, track_matches), total)
    img = np.searchsorted(np.asarray(list(offset.values()), np.int64), nodes, side="right") - 1
    n_lab = int(lab.max()) + 1 if lab.size else 0
    has_gt = np.array([k in cams for k in keys], dtype=bool)
    gt_obs = has_gt[img] if img.size else np.zeros(0, bool)
    gt_li = np.unique((lab * len(kps) + img)[gt_obs]) if lab.size else np.zeros(0, np.int64)
    n_gt_img = np.bincount(gt_li // max(len(kps), 1), minlength=n_lab)
    candidate = n_gt_img >= min_track_views
    conflicting = candidate & repeated_image(lab, img, n_lab)
    return _Tracks(nodes=nodes, img=img, gt_obs=gt_obs, lab=lab, candidate=candidate, conflicting=conflicting,
                   measured=candidate & ~conflicting)


def _padded_observations(keys: list, kps: list[np.ndarray], cams: dict, tracks: _Tracks
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The GT observations of the measured tracks as padded ``(T, L)`` arrays: ``K`` and ``R``
    (T, L, 3, 3), ``t`` (T, L, 3), keypoints (T, L, 2) pixels and the valid mask (T, L)."""
    lab, img, nodes = tracks.lab, tracks.img, tracks.nodes
    sel = tracks.measured[lab] & tracks.gt_obs
    order = np.argsort(lab[sel], kind="stable")
    t_lab, t_img, t_node = lab[sel][order], img[sel][order], nodes[sel][order]
    track_ids, t_row = np.unique(t_lab, return_inverse=True)
    T = len(track_ids)
    counts = np.bincount(t_row, minlength=T)
    L = int(counts.max()) if T else 0
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if T else np.zeros(0, np.int64)
    slot = np.arange(len(t_row)) - starts[t_row] if T else np.zeros(0, np.int64)
    Ks = np.stack([cams[k][0] if k in cams else np.eye(3) for k in keys]) if keys else np.zeros((0, 3, 3))
    Rs = np.stack([cams[k][1] if k in cams else np.eye(3) for k in keys]) if keys else np.zeros((0, 3, 3))
    ts = np.stack([cams[k][2] if k in cams else np.zeros(3) for k in keys]) if keys else np.zeros((0, 3))
    Kp = np.broadcast_to(np.eye(3), (T, L, 3, 3)).copy()
    Rp = np.broadcast_to(np.eye(3), (T, L, 3, 3)).copy()
    tp = np.zeros((T, L, 3))
    xy = np.zeros((T, L, 2))
    valid = np.zeros((T, L), bool)
    if T:
        Kp[t_row, slot], Rp[t_row, slot], tp[t_row, slot] = Ks[t_img], Rs[t_img], ts[t_img]
        xy[t_row, slot] = np.concatenate(kps)[t_node]
        valid[t_row, slot] = True
    return Kp, Rp, tp, xy, valid
