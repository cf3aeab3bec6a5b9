"""The paper's per-pair match metrics (Sec. 4.1.3, App. F) that are not pose metrics.

* precision / recall averaged over the thresholds t = 1..16 px (GT epipolar distance, or
  transfer error for planar pairs), recall relative to the unfiltered input's inliers;
* homography error of a least-squares homography against the GT one, and its AUC at
  5, 10, 15 px.

Pose AUCs live in :mod:`colmap_miho.reporting.pose_metrics`; all points are (N, 2) pixels,
integer = pixel centre.
"""

from __future__ import annotations

import numpy as np

from colmap_miho.reporting.pose_metrics import pose_auc

PR_THRESHOLDS_PX: tuple[float, ...] = tuple(float(t) for t in range(1, 17))
"""Thresholds whose precision / recall are averaged (pixels)."""

H_AUC_THRESHOLDS_PX: tuple[float, ...] = (5.0, 10.0, 15.0)
"""Thresholds of the homography AUC (pixels)."""


def averaged_precision_recall(
    err_input: np.ndarray, kept: np.ndarray, err_kept: np.ndarray | None = None,
    thresholds: tuple[float, ...] = PR_THRESHOLDS_PX,
) -> tuple[float, float]:
    """Precision and recall averaged over ``thresholds``.

    Args:
        err_input: (N,) GT error of every unfiltered input match (pixels).
        kept: (N,) bool, the matches the filter kept.
        err_kept: (N,) GT error after refinement (only the kept rows are read); defaults to
            ``err_input``.

    Returns:
        (precision, recall). Precision is 0 when nothing is kept; recall is nan when the input
        has no inlier at any threshold. Recall may exceed 1 after refinement.
    """
    err_input = np.asarray(err_input, dtype=np.float64)
    kept = np.asarray(kept, dtype=bool)
    err_kept = err_input if err_kept is None else np.asarray(err_kept, dtype=np.float64)
    if err_input.shape != kept.shape or err_kept.shape != kept.shape:
        raise ValueError(
            f"err_input, kept and err_kept must share one shape, got {err_input.shape}, "
            f"{kept.shape}, {err_kept.shape}"
        )
    precisions, recalls = [], []
    n_kept = int(kept.sum())
    for t in thresholds:
        good_kept = int(np.sum(err_kept[kept] <= t))
        good_in = int(np.sum(err_input <= t))
        precisions.append(good_kept / n_kept if n_kept else 0.0)
        recalls.append(good_kept / good_in if good_in else np.nan)
    recall = float(np.nanmean(recalls)) if np.any(np.isfinite(recalls)) else float("nan")
    return float(np.mean(precisions)), recall


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.c_[pts, np.ones(len(pts))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:]


def _grid(shape: tuple[int, int], step: int) -> np.ndarray:
    h, w = shape
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    return np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)


def _one_way(H_est, H_gt, shape_src, shape_dst, step):
    pts = _grid(shape_src, step)
    gt = _apply(H_gt, pts)
    h, w = shape_dst
    inside = (np.isfinite(gt).all(1) & (gt[:, 0] >= -0.5) & (gt[:, 0] <= w - 0.5)
              & (gt[:, 1] >= -0.5) & (gt[:, 1] <= h - 0.5))
    if not inside.any():
        return np.inf
    est = _apply(H_est, pts[inside])
    d = np.linalg.norm(est - gt[inside], axis=1)
    return float(np.mean(np.where(np.isfinite(d), d, 1e9)))


def homography_error(
    H_est: np.ndarray | None, H_gt: np.ndarray, shape1: tuple[int, int], shape2: tuple[int, int], step: int = 4
) -> float:
    """Paper's planar error: mean distance between the estimated and GT mapping over the pixels
    of image 1 that land inside image 2, the same the other way, and the max of the two.

    Args:
        H_est, H_gt: (3, 3) H_2from1 (``None`` for a failed estimate gives ``inf``).
        shape1, shape2: (H, W) of image 1 and image 2.
        step: pixel grid stride (4 keeps it fast; the mean changes by far less than 0.1 px).
    """
    if H_est is None or not np.all(np.isfinite(H_est)) or abs(np.linalg.det(H_est)) < 1e-12:
        return float("inf")
    fwd = _one_way(H_est, H_gt, shape1, shape2, step)
    bwd = _one_way(np.linalg.inv(H_est), np.linalg.inv(H_gt), shape2, shape1, step)
    return max(fwd, bwd)


def homography_from_matches(pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray | None:
    """Least-squares homography (``cv2.findHomography(method=0)``) or None with < 4 matches."""
    import cv2

    if len(pts1) < 4:
        return None
    H, _ = cv2.findHomography(np.asarray(pts1, np.float64), np.asarray(pts2, np.float64), 0)
    return H


def homography_auc(errors, thresholds: tuple[float, ...] = H_AUC_THRESHOLDS_PX) -> dict:
    """``{"auc5", "auc10", "auc15"}`` of planar errors in pixels (failures are ``inf``)."""
    values = pose_auc(errors, thresholds)
    return {f"auc{int(t)}": v for t, v in zip(thresholds, values, strict=True)}
