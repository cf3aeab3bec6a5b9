"""Pose errors of a reconstruction against GT cameras: relative errors over GT pairs and absolute
errors after a similarity alignment of the camera centres (degrees)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from ..geometry import relative_pose
from . import pose_metrics as pm
from .gt_model import CameraPose


def gt_pairs(gt: dict[str, CameraPose]) -> list[tuple[str, str]]:
    """All pairs of GT image names, (name1 < name2), sorted."""
    return list(itertools.combinations(sorted(gt), 2))


def model_pair_errors(
    est: dict[str, CameraPose], gt: dict[str, CameraPose], pairs: list[tuple[str, str]] | None = None
) -> dict[tuple[str, str], float]:
    """Relative-pose error in degrees of each GT pair (default all); ``inf`` for an unregistered image."""
    out = {}
    for a, b in pairs if pairs is not None else gt_pairs(gt):
        if a not in est or b not in est:
            out[(a, b)] = math.inf
            continue
        R_gt, t_gt = relative_pose((gt[a].R, gt[a].t), (gt[b].R, gt[b].t))
        R_es, t_es = relative_pose((est[a].R, est[a].t), (est[b].R, est[b].t))
        out[(a, b)] = pm.pose_error_deg(R_es, t_es, R_gt, t_gt, fold=False)
    return out


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``dst ~ s R src + t`` in least squares (Umeyama 1991) of ``(N, 3)`` points, N >= 3."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"src and dst must be the same (N>=3, 3) shape, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def absolute_errors(est: dict[str, CameraPose], gt: dict[str, CameraPose]) -> dict:
    """Rotation (deg) and centre errors (GT units) after an Umeyama alignment of the centres: a dict
    of statistics with ``center_error_rel`` unit-free; NaNs with fewer than 3 common images."""
    names = sorted(set(est) & set(gt))
    nan = float("nan")
    empty = {"num_aligned": len(names), "scale": nan, "rotation_error_deg": {"median": nan, "mean": nan, "max": nan},
             "center_error": {"median": nan, "mean": nan, "max": nan}, "center_error_rel": nan}
    if len(names) < 3:
        return empty
    c_est = np.array([est[n].center for n in names])
    c_gt = np.array([gt[n].center for n in names])
    try:
        s, R, t = umeyama(c_est, c_gt)
    except np.linalg.LinAlgError:
        return empty
    c_al = (s * (R @ c_est.T)).T + t
    cerr = np.linalg.norm(c_al - c_gt, axis=1)
    # world-to-camera rotation in the GT frame: R_est R^T
    rerr = np.array([pm.rotation_error_deg(est[n].R @ R.T, gt[n].R) for n in names])
    spread = float(np.median(np.linalg.norm(c_gt - c_gt.mean(0), axis=1)))

    def stats(x):
        return {"median": float(np.median(x)), "mean": float(np.mean(x)), "max": float(np.max(x))}

    return {
        "num_aligned": len(names), "scale": s, "rotation_error_deg": stats(rerr), "center_error": stats(cerr),
        "center_error_rel": float(np.median(cerr) / spread) if spread > 0 else nan,
    }
