"""Two-view geometry in numpy: poses, rotation angles, essential and fundamental matrices,
symmetric epipolar distances, fundamental-matrix fitting and epipolar transfer.

Conventions: a pose is ``cam_from_world`` ``(R (3, 3), t (3,))`` (``X_cam = R X + t``); a
relative pose ``cam2_from_cam1``; points are float ``(M, 2)`` (pixels, or normalised
coordinates ``K^-1 x`` with an essential matrix); ``F_2from1`` satisfies ``x2^T F_2from1 x1 = 0``
(homogeneous points), so ``F_2from1 @ x1`` is x1's epipolar line in image 2 and ``F_2from1.T``
is ``F_1from2``. Angles are in degrees.
"""

from __future__ import annotations

import math

import numpy as np

from .types import Pose

#: Matches a fundamental matrix needs (the eight-point algorithm).
MIN_F_MATCHES = 8
#: Correspondences (spread over the rows) on which the sampled hypotheses are scored.
SCORE_POINTS = 300
#: Hypotheses solved and scored together in :func:`fit_fundamental`.
HYPOTHESIS_BATCH = 32
#: Probability that :func:`fit_fundamental` has scored an all-inlier sample when it stops early.
CONFIDENCE = 0.999


def spread_rows(n: int, cap: int) -> np.ndarray:
    """At most ``cap`` row indices int64, spread evenly over ``n`` rows (all of them when
    ``n <= cap``)."""
    return np.arange(n, dtype=np.int64) if n <= cap else np.linspace(0, n - 1, cap).round().astype(np.int64)


def skew(t: np.ndarray) -> np.ndarray:
    """``(3, 3)`` cross-product matrix ``[t]_x`` of ``t`` ``(3,)``."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def relative_pose(pose1: Pose, pose2: Pose) -> Pose:
    """``cam2_from_cam1`` of two ``cam_from_world`` poses: ``R = R2 R1^T``, ``t = t2 - R t1``."""
    R = np.asarray(pose2[0], np.float64) @ np.asarray(pose1[0], np.float64).T
    return R, np.asarray(pose2[1], np.float64).reshape(3) - R @ np.asarray(pose1[1], np.float64).reshape(3)


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Geodesic angle (degrees, in [0, 180]) between two ``(3, 3)`` rotations: the angle of
    ``Ra^T Rb``, as atan2 of its sine and cosine (accurate near 0 too, where the arccos of the
    trace is not)."""
    M = np.asarray(Ra, np.float64).T @ np.asarray(Rb, np.float64)
    sin = 0.5 * np.linalg.norm([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    cos = (np.trace(M) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(sin, cos)))


def essential(rel: Pose) -> np.ndarray:
    """``E_2from1`` ``(3, 3)`` of a relative pose (translation normalised; zero baseline gives
    a zero matrix, whose distances are then undefined and come out as ``inf``)."""
    R, t = rel
    n = float(np.linalg.norm(t))
    return skew(t / n) @ R if n > 0 else np.zeros((3, 3))


def fundamental_from_poses(K1, R1, t1, K2, R2, t2) -> np.ndarray:
    """``F_2from1`` ``(3, 3)`` of two cameras (intrinsics ``K``, ``cam_from_world`` ``R, t``)."""
    R, t = relative_pose((R1, t1), (R2, t2))
    return np.linalg.inv(K2).T @ skew(t) @ R @ np.linalg.inv(K1)


def symmetric_epipolar_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distances ``(d(x2, F x1) + d(x1, F^T x2)) / 2`` of
    correspondences ``x1, x2`` ``(M, 2)`` under ``F_2from1`` (pixels; an essential matrix and
    normalised coordinates give normalised units): ``(M,)``, ``inf`` where a line is undefined."""
    x1 = np.asarray(x1, np.float64).reshape(-1, 2)
    x2 = np.asarray(x2, np.float64).reshape(-1, 2)
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    l2 = h1 @ F.T  # lines in image 2
    l1 = h2 @ F  # lines in image 1
    num = np.abs(np.sum(h2 * l2, axis=1))
    n2 = np.hypot(l2[:, 0], l2[:, 1])
    n1 = np.hypot(l1[:, 0], l1[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 0.5 * (num / n2 + num / n1)
    d[~np.isfinite(d)] = np.inf
    return d


def draws_for_confidence(p_clean: float, confidence: float) -> float:
    """The classical RANSAC bound: random samples to draw so that at least one is all
    inliers with probability ``confidence``, when one sample is with probability
    ``p_clean`` (``inf`` when none can be, 0 when every one is)."""
    if p_clean <= 0:
        return math.inf
    if p_clean >= 1:
        return 0.0
    return math.log(1.0 - confidence) / math.log1p(-p_clean)


def _normalise(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalisation: homogeneous points ``(M, 3)`` with centroid 0 and mean
    distance sqrt(2), and the ``(3, 3)`` transform that did it."""
    c = x.mean(0)
    s = np.sqrt(2.0) / max(float(np.mean(np.linalg.norm(x - c, axis=1))), 1e-12)
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return np.column_stack([(x - c) * s, np.ones(len(x))]), T


def _rank2(F: np.ndarray) -> np.ndarray:
    """Closest rank-2 matrices of ``(..., 3, 3)`` (smallest singular value set to 0)."""
    u, s, vt = np.linalg.svd(F)
    s[..., 2] = 0.0
    return (u * s[..., None, :]) @ vt


def _solve(h1: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Eight-point solutions of ``(..., K, 3)`` normalised correspondences: ``(..., 3, 3)``."""
    A = (h2[..., :, None] * h1[..., None, :]).reshape(*h1.shape[:-1], 9)
    _, vec = np.linalg.eigh(np.swapaxes(A, -1, -2) @ A)  # null vector: the smallest eigenvalue's
    return _rank2(vec[..., :, 0].reshape(*h1.shape[:-2], 3, 3))


def sampson_sq(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Squared Sampson distances (px^2) of ``(M, 2)`` correspondences under ``F_2from1``
    ``(..., 3, 3)``: shape ``(..., M)``.

    All matrices' epipolar lines come from two matrix products over the stacked rows of the
    ``F`` (one for ``F x1``, one for the first two rows of ``F^T x2``), not one small product
    per matrix: scoring many RANSAC hypotheses at once is then one BLAS call each way."""
    F = np.asarray(F, np.float64)
    lead = F.shape[:-2]
    Fs = F.reshape(-1, 3, 3)
    n, m = len(Fs), len(x1)
    h1 = np.column_stack([x1, np.ones(m)])
    h2 = np.column_stack([x2, np.ones(m)])
    Fx1 = (Fs.reshape(-1, 3) @ h1.T).reshape(n, 3, m)  # epipolar lines of x1 in image 2
    Ftx2 = (np.swapaxes(Fs, 1, 2)[:, :2].reshape(-1, 3) @ h2.T).reshape(n, 2, m)  # of x2 in image 1, (a, b)
    num = (Fx1[:, 0] * h2[:, 0] + Fx1[:, 1] * h2[:, 1] + Fx1[:, 2]) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return (num / np.maximum(den, 1e-30)).reshape(*lead, m)


def hypotheses_needed(inlier_share: float, confidence: float) -> float:
    """Eight-point samples to draw so that at least one is all inliers with probability
    ``confidence``, given an inlier share in [0, 1] (the classical RANSAC bound of
    :func:`draws_for_confidence`); 1 when every match is an
    inlier, ``inf`` without inliers."""
    if inlier_share >= 1.0:
        return 1.0
    return draws_for_confidence(inlier_share**MIN_F_MATCHES, confidence)


def fit_fundamental(x1: np.ndarray, x2: np.ndarray, rng: np.random.Generator, *, hypotheses: int = 128,
                    threshold_px: float = 1.5, max_points: int = 1000, batch: int = HYPOTHESIS_BATCH,
                    confidence: float = CONFIDENCE) -> np.ndarray | None:
    """``F_2from1`` ``(3, 3)`` of correspondences ``x1, x2`` ``(M, 2)`` pixels: the best of
    at most ``hypotheses`` random eight-point samples by inlier count (Sampson distance below
    ``threshold_px``), refitted to its inliers; None with fewer than :data:`MIN_F_MATCHES`
    matches or inliers. At most ``max_points`` correspondences (spread over the rows) are used.

    The samples are drawn at once and scored ``batch`` at a time; the search stops early once
    the best inlier share so far makes an all-inlier sample among those scored likely
    (:func:`hypotheses_needed` at ``confidence``). The filtered matches the pair check fits
    are mostly inliers, so one batch usually suffices."""
    x1 = np.asarray(x1, np.float64)
    x2 = np.asarray(x2, np.float64)
    if len(x1) > max_points:
        keep = spread_rows(len(x1), max_points)
        x1, x2 = x1[keep], x2[keep]
    m = len(x1)
    if m < MIN_F_MATCHES:
        return None
    h1, T1 = _normalise(x1)
    h2, T2 = _normalise(x2)
    if m == MIN_F_MATCHES:
        samples = np.arange(m)[None]
    else:  # a sample that repeats a row is degenerate and simply scores low
        samples = rng.integers(0, m, (hypotheses, MIN_F_MATCHES))
    score = spread_rows(m, SCORE_POINTS)  # hypotheses scored on these
    best_F, best_count = np.zeros((3, 3)), -1  # replaced by the first batch's best
    for start in range(0, len(samples), max(batch, 1)):
        chunk = samples[start:start + max(batch, 1)]
        Fs = T2.T @ _solve(h1[chunk], h2[chunk]) @ T1
        counts = (sampson_sq(Fs, x1[score], x2[score]) < threshold_px**2).sum(1)
        top = int(np.argmax(counts))
        if counts[top] > best_count:
            best_F, best_count = Fs[top], int(counts[top])
        if start + len(chunk) >= hypotheses_needed(best_count / len(score), confidence):
            break
    best = sampson_sq(best_F, x1, x2) < threshold_px**2
    for _ in range(2):  # refit to the inliers, twice (the inlier set grows with a better F)
        if best.sum() < MIN_F_MATCHES:
            return None
        F = T2.T @ _solve(h1[best][None], h2[best][None])[0] @ T1
        best = sampson_sq(F, x1, x2) < threshold_px**2
    return F / max(float(np.linalg.norm(F)), 1e-30)


def fit_model_lsq(x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Least-squares two-view model of correspondences that are all inliers (the kept matches
    written to a database): ``(F_2from1, None)`` from the eight-point algorithm, or, when F
    cannot be fitted (fewer than 8 matches, degenerate), ``(None, H_2from1)`` a homography (the
    identity when that fails too)."""
    import cv2

    F = None
    if len(x1) >= MIN_F_MATCHES:
        F, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)
    if F is not None and F.shape == (3, 3) and np.all(np.isfinite(F)):
        return F, None
    H = None
    if len(x1) >= 4:
        H, _ = cv2.findHomography(x1, x2, 0)
    return None, (H if H is not None and np.all(np.isfinite(H)) else np.eye(3))


def transfer(F_3from1: np.ndarray, F_3from2: np.ndarray, x1: np.ndarray,
             x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Epipolar transfer of correspondences ``x1 <-> x2`` ``(M, 2)`` into a third image: the
    intersection of their two epipolar lines there.

    Returns:
        ``(points (M, 2) pixels, sin_angle (M,))``: the sine of the angle between the two
        lines (near 0 when the three camera centres are nearly collinear, or the point
        near their plane's trace: the transfer is then ill-conditioned); rows whose lines do
        not meet get ``nan`` points.
    """
    l1 = np.column_stack([x1, np.ones(len(x1))]) @ F_3from1.T
    l2 = np.column_stack([x2, np.ones(len(x2))]) @ F_3from2.T
    p = np.column_stack([l1[:, 1] * l2[:, 2] - l1[:, 2] * l2[:, 1],  # the lines' cross product, written out
                         l1[:, 2] * l2[:, 0] - l1[:, 0] * l2[:, 2],
                         l1[:, 0] * l2[:, 1] - l1[:, 1] * l2[:, 0]])
    n1 = np.hypot(l1[:, 0], l1[:, 1])
    n2 = np.hypot(l2[:, 0], l2[:, 1])
    sin = np.abs(l1[:, 0] * l2[:, 1] - l1[:, 1] * l2[:, 0]) / np.maximum(n1 * n2, 1e-30)
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = p[:, :2] / p[:, 2:3]
    pts[~np.isfinite(pts).all(1)] = np.nan
    return pts, sin


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to a (3, 3) matrix, via SVD with det = +1."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
