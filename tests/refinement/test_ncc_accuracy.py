"""NCC refinement accuracy on known motion, without ../shared/data: a photograph shipped by
scikit-image, warped by a known homography, keypoints perturbed by known sub-pixel offsets.
Also the local affine rectification on matches of a known homography."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.refinement.config import NCCConfig
from colmap_miho.refinement.pairwise import refine_pair
from colmap_miho.refinement.rectify.local_affine import local_affine_pairs
from miho_bench.variants import variant

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")

# Input keypoints of the moving image are off the truth by up to this much (uniform in x and
# y): errors a detector makes at a sub-pixel level.
INPUT_OFFSET_PX = 0.8
# Median error of the refined keypoints (measured on the camera man photo: 0.02-0.03 px with
# the exact homography pair, 0.03-0.04 px with local affine fits to noisy matches); a
# refinement that is not better than a tenth of a pixel has lost its point.
MAX_MEDIAN_ERROR_PX = 0.10
# Share of the refined keypoints that must end closer to the truth than they started.
MIN_SHARE_IMPROVED = 0.85


def _scene(seed=0, n=300):
    """(image 1, image 2 = image 1 warped by H, H (image 1 -> image 2), keypoints in image 1
    on textured spots, their true positions in image 2)."""
    img1 = skdata.camera().astype(np.float32) / 255.0
    H = np.array([[0.97, 0.06, 9.3], [-0.04, 1.02, -6.7], [2e-5, -3e-5, 1.0]])
    # cv2 maps pixel centres at integers, like colmap-miho
    img2 = cv2.warpPerspective(img1, H, img1.shape[::-1], flags=cv2.INTER_CUBIC)
    rng = np.random.default_rng(seed)
    corners = cv2.goodFeaturesToTrack((img1 * 255).astype(np.uint8), 2000, 0.01, 5)[:, 0]
    inside = np.all((corners > 40) & (corners < np.array(img1.shape[::-1]) - 40), axis=1)
    pts1 = corners[inside][:n].astype(np.float64) + rng.uniform(-0.5, 0.5, (min(n, inside.sum()), 2))
    x = np.c_[pts1, np.ones(len(pts1))] @ H.T
    truth2 = x[:, :2] / x[:, 2:]
    return img1, img2, H, pts1, truth2, rng


def _check(res, start, truth):
    before = np.linalg.norm(start - truth, axis=1)
    after = np.linalg.norm(res.pts2 - truth, axis=1)
    moved = res.moved_side == 2
    assert moved.mean() > 0.8
    assert np.median(after[moved]) <= MAX_MEDIAN_ERROR_PX
    assert (after[moved] < before[moved]).mean() >= MIN_SHARE_IMPROVED
    return float(np.median(before)), float(np.median(after))


def test_ncc_recovers_known_subpixel_shifts_with_the_exact_homography():
    img1, img2, H, pts1, truth2, rng = _scene()
    start = truth2 + rng.uniform(-INPUT_OFFSET_PX, INPUT_OFFSET_PX, truth2.shape)
    pairs = np.tile(np.stack([np.eye(3), np.linalg.inv(H)]), (len(pts1), 1, 1, 1))
    res = refine_pair(img1, img2, pts1, start, pairs, move="2", config=NCCConfig.pairwise(device="cpu"))
    before, after = _check(res, start, truth2)
    assert after < 0.25 * before


def test_ncc_with_local_affine_rectification_from_noisy_matches():
    """The rectification comes from the matches themselves (0.3 px noise), as in the walk."""
    img1, img2, _H, pts1, truth2, rng = _scene(seed=1)
    start = truth2 + rng.uniform(-INPUT_OFFSET_PX, INPUT_OFFSET_PX, truth2.shape)
    noisy = truth2 + rng.normal(0, 0.3, truth2.shape)
    identity = np.tile(np.eye(3), (1, 2, 1, 1))
    pairs = local_affine_pairs(pts1, noisy, np.zeros(len(pts1), np.int64), identity, k=12,
                               max_residual_px=2.0)
    res = refine_pair(img1, img2, pts1, start, pairs, move="2",
                      config=variant(NCCConfig.pairwise(device="cpu"), use_base_pair=False))
    _check(res, start, truth2)


# local affine fits of exact matches of a homography: the linear part of each fit is the
# homography's Jacobian at the match to within this relative error (the fit spans the match's
# nearest neighbours, so the homography's curvature makes up the rest; measured 0.2-0.4%).
MAX_LOCAL_JACOBIAN_ERROR = 0.01


def _jacobians(H, x):
    y = np.c_[x, np.ones(len(x))] @ H.T
    w = y[:, 2]
    u = y[:, :2] / w[:, None]
    return (H[None, :2, :2] - u[:, :, None] * H[None, 2:, :2]) / w[:, None, None]


def _linear_parts(pairs):
    return np.linalg.inv(pairs[:, 1])[:, :2, :2]


def test_local_affine_pairs_fit_a_known_homography():
    rng = np.random.default_rng(2)
    H = np.array([[1.1, 0.05, 3.0], [-0.02, 0.95, 1.0], [1e-4, 5e-5, 1.0]])
    x1 = rng.uniform(0, 500, (400, 2))
    y = np.c_[x1, np.ones(len(x1))] @ H.T
    x2 = y[:, :2] / y[:, 2:]
    labels = np.where(np.arange(400) < 395, 0, -1)
    eye = np.tile(np.eye(3), (1, 2, 1, 1))
    pairs = local_affine_pairs(x1, x2, labels, eye, k=12, max_residual_px=2.0)
    J = _jacobians(H, x1[:395])
    err = np.linalg.norm(_linear_parts(pairs[:395]) - J, axis=(1, 2)) / np.linalg.norm(J, axis=(1, 2))
    assert err.max() < MAX_LOCAL_JACOBIAN_ERROR
    np.testing.assert_array_equal(pairs[:395, 0], np.tile(np.eye(3), (395, 1, 1)))
    np.testing.assert_array_equal(pairs[395:], np.tile(np.eye(3), (5, 2, 1, 1)))
    # a gross outlier among the neighbours is dropped by the second fit
    x2o = x2.copy()
    x2o[0] += 25.0
    pairs_o = local_affine_pairs(x1, x2o, labels, eye, k=12, max_residual_px=2.0)
    near = np.argsort(np.linalg.norm(x1[:395] - x1[0], axis=1))[1:6]
    err = (np.linalg.norm(_linear_parts(pairs_o[near]) - J[near], axis=(1, 2))
           / np.linalg.norm(J[near], axis=(1, 2)))
    assert err.max() < MAX_LOCAL_JACOBIAN_ERROR
    # too few matches in a cluster: the filter's pair is kept
    few = local_affine_pairs(x1[:4], x2[:4], np.zeros(4, np.int64), 2 * eye, k=12,
                             max_residual_px=2.0)
    np.testing.assert_array_equal(few, np.tile(2 * np.eye(3), (4, 2, 1, 1)))


def test_local_affine_pairs_of_some_matches_are_those_of_all():
    """Fitting only some matches (``fit``) gives them bitwise the pairs of fitting every
    match (neighbours still drawn from the whole cluster; clusters of different sizes are
    batched together); the others keep the filter's pair."""
    rng = np.random.default_rng(5)
    H = np.array([[1.05, 0.03, 2.0], [-0.01, 0.97, -1.0], [5e-5, -2e-5, 1.0]])
    x1 = rng.uniform(0, 400, (300, 2))
    y = np.c_[x1, np.ones(len(x1))] @ H.T
    x2 = y[:, :2] / y[:, 2:] + rng.normal(0, 0.3, (300, 2))
    # clusters of 200, 60, 8 (fewer neighbours than k) and 4 (too few: no fit) matches
    labels = np.repeat([0, 1, 2, 3, -1], [200, 60, 8, 4, 28])
    homs = np.stack([np.stack([np.eye(3), np.eye(3) * (1 + c)]) for c in range(4)])
    full = local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0)
    fit = rng.random(300) < 0.4
    part = local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0, fit=fit)
    np.testing.assert_array_equal(part[fit], full[fit])
    kept = ~fit & (labels >= 0)
    np.testing.assert_array_equal(part[kept], homs[labels[kept]])
    assert (full[kept] != part[kept]).any()  # those would have been fitted
    np.testing.assert_array_equal(part[labels < 0], np.tile(np.eye(3), (28, 2, 1, 1)))
