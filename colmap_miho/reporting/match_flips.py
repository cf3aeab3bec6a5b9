"""Matches that refinement turned wrong (or right) under ground-truth geometry: the same keypoint
indices before and after, beyond (within) ``threshold_px`` of the GT epipolar line only after."""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping
from dataclasses import asdict, dataclass

import numpy as np

from ..geometry import fundamental_from_poses, symmetric_epipolar_distance
from .keypoint_accuracy import TRACK_THRESHOLD_PX, camera_krt

FLIP_THRESHOLD_PX = TRACK_THRESHOLD_PX
"""A match within this distance (px, symmetric) of its GT epipolar line counts as correct: the
threshold of a wrong track (:data:`~colmap_miho.reporting.keypoint_accuracy.TRACK_THRESHOLD_PX`)."""


@dataclass(frozen=True)
class FlipCases:
    """Every match stored in both databases between two GT images (M rows): ``pair`` into ``pairs``,
    ``idx`` ``(M, 2)``, GT epipolar distances ``before``/``after`` (px), ``disp`` ``(M, 2)`` moves."""

    pair: np.ndarray
    pairs: list
    idx: np.ndarray
    before: np.ndarray
    after: np.ndarray
    disp: np.ndarray

    def turned_wrong(self, threshold_px: float = FLIP_THRESHOLD_PX) -> np.ndarray:
        """(M,) bool: within ``threshold_px`` before, beyond it after."""
        return (self.before <= threshold_px) & (self.after > threshold_px)

    def turned_right(self, threshold_px: float = FLIP_THRESHOLD_PX) -> np.ndarray:
        """(M,) bool: beyond ``threshold_px`` before, within it after."""
        return (self.before > threshold_px) & (self.after <= threshold_px)


@dataclass(frozen=True, kw_only=True)
class EpipolarFlips:
    """Summary of :class:`FlipCases`: counts and displacement statistics (per match the larger of
    its keypoints' moves) of the turned-wrong and turned-right matches; NaN where nothing was
    counted."""

    num_compared: int
    num_moved: int
    num_turned_wrong: int
    num_turned_right: int
    wrong_disp_median_px: float
    wrong_disp_p90_px: float
    wrong_disp_max_px: float
    right_disp_median_px: float
    right_disp_max_px: float
    moved_disp_median_px: float
    threshold_px: float

    def to_dict(self) -> dict:
        """Plain dict with the attribute names as keys, NaN as None (JSON-ready)."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}


def epipolar_flip_cases(
    cameras: Mapping[Hashable, object],
    keypoints_before: Mapping[Hashable, np.ndarray],
    keypoints_after: Mapping[Hashable, np.ndarray],
    matches_before: Mapping[tuple[Hashable, Hashable], np.ndarray],
    matches_after: Mapping[tuple[Hashable, Hashable], np.ndarray],
) -> FlipCases:
    """The matches stored in both databases between two GT images, with GT epipolar distances before
    and after and their keypoints' displacements.

    An image's two keypoint arrays must have the same rows; a pair counts in the orientation given.
    ValueError names an image whose arrays differ or a pair with an index out of range."""
    cams = {k: camera_krt(c) for k, c in cameras.items()}
    pairs: list[tuple[Hashable, Hashable]] = []
    rows: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for (a, b), m0 in matches_before.items():
        m1 = matches_after.get((a, b))
        if m1 is None or a not in cams or b not in cams:
            continue
        for key in (a, b):
            k0, k1 = keypoints_before.get(key), keypoints_after.get(key)
            if k0 is None or k1 is None or np.shape(k0) != np.shape(k1):
                raise ValueError(f"image {key!r}: keypoints missing or of another shape before and after")
        common = _common_rows(np.asarray(m0, np.int64).reshape(-1, 2), np.asarray(m1, np.int64).reshape(-1, 2))
        if common.size == 0:
            continue
        ka0, kb0 = (np.asarray(keypoints_before[k], np.float64).reshape(-1, 2) for k in (a, b))
        ka1, kb1 = (np.asarray(keypoints_after[k], np.float64).reshape(-1, 2) for k in (a, b))
        if common.min() < 0 or common[:, 0].max() >= len(ka0) or common[:, 1].max() >= len(kb0):
            raise ValueError(f"pair ({a!r}, {b!r}): match index out of range")
        F = fundamental_from_poses(*cams[a], *cams[b])
        before = symmetric_epipolar_distance(F, ka0[common[:, 0]], kb0[common[:, 1]])
        after = symmetric_epipolar_distance(F, ka1[common[:, 0]], kb1[common[:, 1]])
        disp = np.stack([np.linalg.norm(ka1[common[:, 0]] - ka0[common[:, 0]], axis=1),
                         np.linalg.norm(kb1[common[:, 1]] - kb0[common[:, 1]], axis=1)], axis=1)
        rows.append((len(pairs), common, before, after, disp))
        pairs.append((a, b))
    if not rows:
        z = np.zeros(0)
        return FlipCases(np.zeros(0, np.int64), pairs, np.zeros((0, 2), np.int64), z, z, np.zeros((0, 2)))
    return FlipCases(
        pair=np.concatenate([np.full(len(r[1]), r[0], np.int64) for r in rows]),
        pairs=pairs,
        idx=np.concatenate([r[1] for r in rows]),
        before=np.concatenate([r[2] for r in rows]),
        after=np.concatenate([r[3] for r in rows]),
        disp=np.concatenate([r[4] for r in rows]),
    )


def _common_rows(m0: np.ndarray, m1: np.ndarray) -> np.ndarray:
    if m0.size == 0 or m1.size == 0:
        return np.zeros((0, 2), np.int64)
    if min(m0.min(), m1.min()) < 0:
        raise ValueError("negative keypoint index in a match")
    width = int(max(m0[:, 1].max(), m1[:, 1].max())) + 1
    k0 = m0[:, 0] * width + m0[:, 1]
    k1 = m1[:, 0] * width + m1[:, 1]
    both = np.intersect1d(k0, k1)
    return np.stack([both // width, both % width], axis=1)


def summarize_flips(cases: FlipCases, threshold_px: float = FLIP_THRESHOLD_PX) -> EpipolarFlips:
    """:class:`EpipolarFlips` of ``cases`` at ``threshold_px`` (> 0, else ValueError)."""
    if not threshold_px > 0:
        raise ValueError(f"threshold_px must be > 0, got {threshold_px}")
    nan = float("nan")
    moved = cases.disp.max(axis=1) if len(cases.disp) else np.zeros(0)
    wrong = moved[cases.turned_wrong(threshold_px)]
    right = moved[cases.turned_right(threshold_px)]
    moving = moved[moved > 1e-6]

    def stat(x: np.ndarray, q: float) -> float:
        return float(np.quantile(x, q)) if x.size else nan

    return EpipolarFlips(
        num_compared=int(cases.before.size),
        num_moved=int(moving.size),
        num_turned_wrong=int(wrong.size),
        num_turned_right=int(right.size),
        wrong_disp_median_px=stat(wrong, 0.5),
        wrong_disp_p90_px=stat(wrong, 0.9),
        wrong_disp_max_px=stat(wrong, 1.0),
        right_disp_median_px=stat(right, 0.5),
        right_disp_max_px=stat(right, 1.0),
        moved_disp_median_px=stat(moving, 0.5),
        threshold_px=float(threshold_px),
    )


def epipolar_flips(
    cameras: Mapping[Hashable, object],
    keypoints_before: Mapping[Hashable, np.ndarray],
    keypoints_after: Mapping[Hashable, np.ndarray],
    matches_before: Mapping[tuple[Hashable, Hashable], np.ndarray],
    matches_after: Mapping[tuple[Hashable, Hashable], np.ndarray],
    *,
    threshold_px: float = FLIP_THRESHOLD_PX,
) -> EpipolarFlips:
    """Turned-wrong and turned-right matches between two databases (arguments as :func:`epipolar_flip_cases`)."""
    if not threshold_px > 0:
        raise ValueError(f"threshold_px must be > 0, got {threshold_px}")
    cases = epipolar_flip_cases(cameras, keypoints_before, keypoints_after, matches_before, matches_after)
    return summarize_flips(cases, threshold_px)
