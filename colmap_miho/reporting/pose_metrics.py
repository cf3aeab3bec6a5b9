"""Pose errors, pose AUC / mAA and the paper's two-view pose protocols (numpy + OpenCV).
World-to-camera poses, ``(N, 2)`` pixels (integer = pixel centre, as ``K``), degrees; a failed
estimate has error ``inf`` and counts as a miss."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..geometry import rotation_angle_deg

log = logging.getLogger(__name__)

AUC_THRESHOLDS_DEG: tuple[float, ...] = (5.0, 10.0, 20.0)
"""Angular thresholds of the pose AUC (degrees)."""

MAA_THRESHOLDS_DEG: tuple[float, ...] = tuple(float(t) for t in range(1, 11))
"""Thresholds of the mean average accuracy (1, 2, ..., 10 degrees)."""


# --------------------------------------------------------------------------- pose errors
def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Geodesic angle between two ``(3, 3)`` rotations, degrees in [0, 180]."""
    R_est = np.asarray(R_est, dtype=np.float64)
    R_gt = np.asarray(R_gt, dtype=np.float64)
    if R_est.shape != (3, 3) or R_gt.shape != (3, 3):
        raise ValueError(f"rotations must be (3, 3), got {R_est.shape} and {R_gt.shape}")
    return rotation_angle_deg(R_est, R_gt)


def translation_angle_deg(t_est: np.ndarray, t_gt: np.ndarray, *, fold: bool = True) -> float:
    """Angle in degrees between two translation directions, ``inf`` for a near-zero vector.

    ``fold`` maps ``e`` to ``min(e, 180 - e)`` for two-view poses of ambiguous sign; use
    ``fold=False`` for a reconstruction's poses."""
    t_est = np.asarray(t_est, dtype=np.float64).reshape(-1)
    t_gt = np.asarray(t_gt, dtype=np.float64).reshape(-1)
    if t_est.shape != (3,) or t_gt.shape != (3,):
        raise ValueError(f"translations must be (3,), got {t_est.shape} and {t_gt.shape}")
    n_est, n_gt = np.linalg.norm(t_est), np.linalg.norm(t_gt)
    if n_est < 1e-12 or n_gt < 1e-12:
        return float("inf")
    cos = float(np.clip(t_est @ t_gt / (n_est * n_gt), -1.0, 1.0))
    err = float(np.degrees(np.arccos(cos)))
    return min(err, 180.0 - err) if fold else err


def pose_error_deg(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, *, fold: bool = True
) -> float:
    """Pose error = max(rotation error, translation-direction angle), degrees."""
    return max(rotation_error_deg(R_est, R_gt), translation_angle_deg(t_est, t_gt, fold=fold))


# --------------------------------------------------------------------------- AUC / mAA
def pose_auc(errors, thresholds=AUC_THRESHOLDS_DEG) -> list[float]:
    """Area under the recall-vs-error curve up to each threshold, divided by it: one AUC in [0, 1]
    per threshold. Failures (``inf``/``nan``) count in N but never reach the curve; N = 0 gives 0."""
    errs = np.asarray(errors, dtype=np.float64).reshape(-1)
    errs = np.where(np.isnan(errs), np.inf, errs)
    n = errs.size
    out: list[float] = []
    for thr in thresholds:
        if thr <= 0:
            raise ValueError(f"thresholds must be positive, got {thr}")
        if n == 0:
            out.append(0.0)
            continue
        e = np.sort(errs)
        recall = np.arange(1, n + 1, dtype=np.float64) / n
        e = np.concatenate([[0.0], e])
        recall = np.concatenate([[0.0], recall])
        last = int(np.searchsorted(e, thr, side="left"))
        xs = np.concatenate([e[:last], [thr]])
        ys = np.concatenate([recall[:last], [recall[last - 1]]])
        out.append(float(np.trapezoid(ys, x=xs) / thr))
    return out


def mean_average_accuracy(errors, thresholds=MAA_THRESHOLDS_DEG) -> float:
    """Mean over thresholds of the share of errors strictly below each, in [0, 1] (N = 0 gives 0)."""
    errs = np.asarray(errors, dtype=np.float64).reshape(-1)
    if errs.size == 0:
        return 0.0
    errs = np.where(np.isnan(errs), np.inf, errs)
    return float(np.mean([np.mean(errs < t) for t in thresholds]))


def auc_summary(errors, thresholds=AUC_THRESHOLDS_DEG) -> dict:
    """``{"auc5", "auc10", "auc20", "maa", "num_pairs", "num_failed"}`` for a set of pair errors."""
    errs = np.asarray(errors, dtype=np.float64).reshape(-1)
    aucs = pose_auc(errs, thresholds)
    out = {f"auc{int(t) if float(t).is_integer() else t}": a for t, a in zip(thresholds, aucs, strict=True)}
    out["maa"] = mean_average_accuracy(errs)
    out["num_pairs"] = int(errs.size)
    out["num_failed"] = int(np.sum(~np.isfinite(errs)))
    return out


# --------------------------------------------------------------------------- two-view protocols
@dataclass(frozen=True, kw_only=True)
class TwoViewPoseResult:
    """Outcome of one two-view pose estimate: ``R``, ``t`` (``cam2_from_cam1``, unit t) or None,
    ``error_deg`` vs GT (``inf`` on failure), matches given and inliers used."""

    success: bool
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    error_deg: float = float("inf")
    num_matches: int = 0
    num_inliers: int = 0
    reason: str = ""


def _check_points(pts1, pts2, K1, K2):
    p1 = np.ascontiguousarray(pts1, dtype=np.float64)
    p2 = np.ascontiguousarray(pts2, dtype=np.float64)
    if p1.ndim != 2 or p1.shape[1] != 2 or p1.shape != p2.shape:
        raise ValueError(f"pts1 and pts2 must both be (N, 2), got {p1.shape} and {p2.shape}")
    K1 = np.asarray(K1, dtype=np.float64)
    K2 = np.asarray(K2, dtype=np.float64)
    if K1.shape != (3, 3) or K2.shape != (3, 3):
        raise ValueError(f"K1 and K2 must be (3, 3), got {K1.shape} and {K2.shape}")
    return p1, p2, K1, K2


def _normalize(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (pts - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def pose_from_essential(
    pts1, pts2, K1, K2, R_gt, t_gt, *, threshold_px: float = 0.5, prob: float = 0.99999,
    max_iters: int = 10000, seed: int = 0,
) -> TwoViewPoseResult:
    """The paper's E protocol: RANSAC essential matrix on K-normalised points, then ``recoverPose``.

    ``threshold_px`` is divided by the mean focal length; the GT pose only scores the estimate;
    ``seed`` seeds OpenCV's RNG. ``success=False`` with fewer than 5 matches or no E."""
    import cv2

    p1, p2, K1, K2 = _check_points(pts1, pts2, K1, K2)
    n = len(p1)
    if n < 5:
        return TwoViewPoseResult(success=False, num_matches=n, reason="fewer than 5 matches")
    n1, n2 = _normalize(p1, K1), _normalize(p2, K2)
    focal = float(np.mean([K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]]))
    cv2.setRNGSeed(int(seed))
    try:
        E, mask = cv2.findEssentialMat(
            n1, n2, np.eye(3), method=cv2.RANSAC, prob=prob, threshold=threshold_px / focal,
            maxIters=int(max_iters),
        )
    except cv2.error as exc:  # degenerate input
        return TwoViewPoseResult(success=False, num_matches=n, reason=f"findEssentialMat: {exc}")
    if E is None or E.shape[0] < 3:
        return TwoViewPoseResult(success=False, num_matches=n, reason="no essential matrix")
    best: tuple[int, np.ndarray, np.ndarray] | None = None
    for k in range(E.shape[0] // 3):
        Ek = E[3 * k: 3 * k + 3]
        # cv2's stubs declare the 5-output overload (with triangulated points) first
        n_in, R, t, _ = cv2.recoverPose(Ek, n1, n2, np.eye(3), 1e9, mask=mask.copy())[:4]
        if best is None or n_in > best[0]:
            best = (int(n_in), R, t.reshape(3))
    assert best is not None  # E holds at least one 3x3 block
    n_in, R, t = best
    err = pose_error_deg(R, t, R_gt, t_gt, fold=True)
    return TwoViewPoseResult(
        success=True, R=R, t=t, error_deg=err, num_matches=n, num_inliers=int(n_in)
    )


def pose_from_fundamental(
    pts1, pts2, K1, K2, R_gt, t_gt, *, magsac: bool = True, magsac_threshold_px: float = 0.75,
    magsac_iters: int = 100000, seed: int = 0,
) -> TwoViewPoseResult:
    """The paper's F protocol: optional MAGSAC, 8-point F, ``E = K2^T F K1``, the decomposition
    closest to the GT pose. ``success=False`` with fewer than 8 remaining matches."""
    import cv2

    p1, p2, K1, K2 = _check_points(pts1, pts2, K1, K2)
    n = len(p1)
    if n < 8:
        return TwoViewPoseResult(success=False, num_matches=n, reason="fewer than 8 matches")
    if magsac:
        cv2.setRNGSeed(int(seed))
        try:
            _, mask = cv2.findFundamentalMat(
                p1, p2, cv2.USAC_MAGSAC, magsac_threshold_px, 0.99999, int(magsac_iters)
            )
        except cv2.error as exc:
            return TwoViewPoseResult(success=False, num_matches=n, reason=f"MAGSAC: {exc}")
        if mask is None:
            return TwoViewPoseResult(success=False, num_matches=n, reason="MAGSAC found no model")
        keep = mask.reshape(-1).astype(bool)
        p1, p2 = p1[keep], p2[keep]
        if len(p1) < 8:
            return TwoViewPoseResult(
                success=False, num_matches=n, num_inliers=len(p1), reason="fewer than 8 MAGSAC inliers"
            )
    try:
        F, _ = cv2.findFundamentalMat(p1, p2, cv2.FM_8POINT)
    except cv2.error as exc:
        return TwoViewPoseResult(success=False, num_matches=n, reason=f"8-point: {exc}")
    if F is None or F.shape != (3, 3):
        return TwoViewPoseResult(success=False, num_matches=n, reason="8-point found no F")
    E = K2.T @ F @ K1
    R_a, R_b, t = cv2.decomposeEssentialMat(E)
    t = t.reshape(3)
    best_err, best_R = np.inf, None
    for R in (R_a, R_b):  # the folded t error makes +t and -t equivalent
        err = pose_error_deg(R, t, R_gt, t_gt, fold=True)
        if err < best_err:
            best_err, best_R = err, R
    return TwoViewPoseResult(
        success=True, R=best_R, t=t, error_deg=float(best_err), num_matches=n, num_inliers=len(p1)
    )
