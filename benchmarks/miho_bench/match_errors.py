"""Ground-truth errors of matches: homography transfer error and epipolar distance.

All points are (N, 2) pixels, integer = pixel centre.
"""

from __future__ import annotations

import numpy as np

from .datasets import PairGT


def _h(pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    return np.concatenate([pts, np.ones((len(pts), 1))], axis=1)


def transfer_error(H_2from1: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """(N,) max(|H x1 - x2|, |H^-1 x2 - x1|) in pixels; inf where a point maps to infinity."""
    H = np.asarray(H_2from1, dtype=np.float64)
    p1, p2 = _h(pts1), _h(pts2)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = p1 @ H.T
        f = f[:, :2] / f[:, 2:]
        b = p2 @ np.linalg.inv(H).T
        b = b[:, :2] / b[:, 2:]
        err = np.maximum(np.linalg.norm(f - p2[:, :2], axis=1), np.linalg.norm(b - p1[:, :2], axis=1))
    return np.where(np.isfinite(err), err, np.inf)


def epipolar_error(F_2from1: np.ndarray, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """(N,) max of the two point-to-epipolar-line distances in pixels (x2^T F x1 = 0)."""
    F = np.asarray(F_2from1, dtype=np.float64)
    p1, p2 = _h(pts1), _h(pts2)
    l2 = p1 @ F.T  # lines in image 2
    l1 = p2 @ F  # lines in image 1
    num = np.abs(np.sum(p2 * l2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num / np.linalg.norm(l2[:, :2], axis=1)
        d1 = num / np.linalg.norm(l1[:, :2], axis=1)
    err = np.maximum(d1, d2)
    return np.where(np.isfinite(err), err, np.inf)


def gt_error(pair: PairGT, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
    """Transfer error for planar pairs, epipolar error for pairs with a pose."""
    if pair.H_2from1 is not None:
        return transfer_error(pair.H_2from1, pts1, pts2)
    F = pair.F_2from1
    if F is None:
        raise ValueError(f"pair {pair.label} has no ground truth")
    return epipolar_error(F, pts1, pts2)


def precision_recall(
    err_before: np.ndarray, kept: np.ndarray, err_after: np.ndarray | None = None, threshold: float = 3.0
) -> tuple[float, float]:
    """Precision of the kept matches and recall relative to the input's GT inliers.

    Args:
        err_before: (N,) GT error of every input match.
        kept: (N,) bool mask of the matches a filter kept.
        err_after: (N,) GT error after refinement (defaults to ``err_before``).
        threshold: pixels.

    Returns:
        (precision, recall); precision is nan when nothing is kept, recall nan when the
        input has no inlier. Recall can exceed 1 after refinement (paper's definition).
    """
    err_after = err_before if err_after is None else err_after
    kept = np.asarray(kept, dtype=bool)
    good_in = int(np.sum(err_before <= threshold))
    good_kept = int(np.sum(err_after[kept] <= threshold))
    precision = good_kept / kept.sum() if kept.sum() else float("nan")
    recall = good_kept / good_in if good_in else float("nan")
    return precision, recall
