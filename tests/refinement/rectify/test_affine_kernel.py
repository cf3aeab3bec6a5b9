"""The compiled local affine fits (:mod:`colmap_miho.refinement.rectify.kernel`) against the
numpy reference (``tests/affine_reference.py``), on synthetic matches of a
homography with noise, gross outliers, duplicate keypoints and degenerate neighbourhoods."""

from __future__ import annotations

import numpy as np
import pytest
from affine_reference import fit_rows, local_affine_pairs_numpy

from colmap_miho.refinement.rectify import kernel as affine_kernel
from colmap_miho.refinement.rectify.local_affine import _ITERATIONS, MIN_NEIGHBOURS, local_affine_pairs

#: maps of kernel and numpy path, relative to the largest entry of their row: the two solve
#: the same normal equations with different rounding (the equations' condition number is
#: about 1e5 on pixel offsets).
MAP_REL_TOL = 1e-9
#: eigenvalues of the closed form against LAPACK's, relative to the largest.
EIGEN_REL_TOL = 1e-12

H_TRUE = np.array([[1.1, 0.05, 3.0], [-0.02, 0.95, 1.0], [1e-4, 5e-5, 1.0]])


def _matches(n: int, seed: int, noise_px: float = 0.3, outliers: int = 20):
    rng = np.random.default_rng(seed)
    x1 = rng.uniform(0, 500, (n, 2))
    x1[n - 10:] = x1[:10]  # duplicate keypoints (SIFT's several orientations)
    y = np.c_[x1, np.ones(n)] @ H_TRUE.T
    x2 = y[:, :2] / y[:, 2:] + rng.normal(0, noise_px, (n, 2))
    x2[rng.choice(n, outliers, replace=False)] += rng.uniform(-40, 40, (outliers, 2))
    # a patch of wrong matches: fits there keep too few neighbours
    bad = np.argsort(np.linalg.norm(x1 - 250.0, axis=1))[:30]
    x2[bad] = rng.uniform(0, 500, (30, 2))
    return x1, x2


def _neighbours(x1: np.ndarray, k: int) -> np.ndarray:
    d = np.linalg.norm(x1[:, None] - x1[None], axis=2)
    return np.argsort(d, axis=1, kind="stable")[:, :k]


@pytest.mark.parametrize("k", [6, 12, 13])
def test_kernel_fits_match_the_numpy_reference(k):
    x1, x2 = _matches(300, seed=k)
    rows = np.arange(300)
    nb = _neighbours(x1, k)
    good_ref, H_ref = fit_rows(x1, x2, rows, nb, 2.0)
    good, H, H_inv = affine_kernel.fit_rows(x1, x2, rows, nb, max_residual_px=2.0,
                                            iterations=_ITERATIONS, min_neighbours=MIN_NEIGHBOURS)
    np.testing.assert_array_equal(good, good_ref)
    assert 0.5 < good.mean() < 1.0  # the outliers make some fits fail
    scale = np.abs(H_ref).max(axis=(1, 2), keepdims=True)
    assert (np.abs(H - H_ref) / scale).max() < MAP_REL_TOL
    np.testing.assert_allclose(H_inv[good], np.linalg.inv(H[good]), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(H_inv[~good], np.tile(np.eye(3), ((~good).sum(), 1, 1)))


def test_kernel_rejects_degenerate_neighbourhoods():
    """Collinear neighbours (ill-conditioned normal matrix) and a folding map (determinant
    <= 0) are not good fits, in both paths."""
    t = np.linspace(0, 50, 12)
    x1 = np.c_[t, 2 * t + 1]  # collinear
    x2 = x1 + 1.0
    x1f = np.random.default_rng(0).uniform(0, 50, (12, 2))
    x2f = x1f[:, ::-1].copy()  # a reflection: det = -1
    for a, b in ((x1, x2), (x1f, x2f)):
        rows, nb = np.arange(12), np.tile(np.arange(12), (12, 1))
        good_ref, _ = fit_rows(a, b, rows, nb, 2.0)
        good, _, H_inv = affine_kernel.fit_rows(a, b, rows, nb, max_residual_px=2.0,
                                                iterations=_ITERATIONS, min_neighbours=MIN_NEIGHBOURS)
        assert not good.any() and not good_ref.any()
        np.testing.assert_array_equal(H_inv, np.tile(np.eye(3), (12, 1, 1)))


def test_extreme_eigenvalues_match_lapack():
    rng = np.random.default_rng(1)
    mats = []
    for _ in range(200):
        X = np.c_[rng.normal(0, rng.uniform(1, 300), (12, 2)), np.ones(12)]
        mats.append(X.T @ X)
    mats.append(np.diag([3.0, 1.0, 2.0]))  # diagonal: the closed form's special case
    mats.append(np.diag([5.0, 5.0, 5.0]))
    for S in mats:
        lo, hi = affine_kernel._extreme_eigenvalues(S)
        ev = np.linalg.eigvalsh(S)
        assert abs(lo - ev[0]) <= EIGEN_REL_TOL * ev[2]
        assert abs(hi - ev[2]) <= EIGEN_REL_TOL * ev[2]


def test_local_affine_pairs_compiled_and_numpy_agree():
    """Whole pairs, clusters of several sizes (fewer matches than k; too few to fit): the
    same pairs within rounding, the same matches fitted."""
    x1, x2 = _matches(300, seed=7)
    labels = np.repeat([0, 1, 2, 3, -1], [200, 60, 8, 4, 28])
    homs = np.stack([np.stack([np.eye(3), np.eye(3) * (1 + c)]) for c in range(4)])
    ref = local_affine_pairs_numpy(x1, x2, labels, homs, k=12, max_residual_px=2.0)
    got = local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0)
    fitted_ref = ~np.all(ref == np.r_[homs, np.eye(3)[None].repeat(2, 0)[None]][labels], axis=(1, 2, 3))
    fitted = ~np.all(got == np.r_[homs, np.eye(3)[None].repeat(2, 0)[None]][labels], axis=(1, 2, 3))
    np.testing.assert_array_equal(fitted, fitted_ref)
    assert fitted[:268].mean() > 0.5
    scale = np.abs(ref).max(axis=(2, 3), keepdims=True)
    assert (np.abs(got - ref) / scale).max() < MAP_REL_TOL


def _brute_neighbours(x1: np.ndarray, rows: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """The k nearest of ``rows`` to each of ``queries`` (rows), nearest first, ties to the
    lower row: the compiled search's rule."""
    out = []
    for q in queries:
        d = ((x1[rows] - x1[q]) ** 2).sum(axis=1)
        out.append(rows[np.lexsort((rows, d))[:k]])
    return np.array(out, np.int64).reshape(len(queries), k)


def test_fit_clusters_are_fits_to_the_nearest_neighbours():
    """The grid search finds exactly the k nearest (ties to the lower row, in that order):
    its fits are bitwise those of :func:`fit_rows` given brute-force neighbours. Clusters: a
    large one with duplicate keypoints and keypoints on a lattice (many equal distances), a
    small one (fewer matches than k), a collinear one, one of identical points, one too
    small to fit."""
    x1, x2 = _matches(400, seed=3)
    x1[300:340] = np.c_[np.repeat(np.arange(5), 8) * 4.0, np.tile(np.arange(8), 5) * 4.0]
    y = np.c_[x1[300:340], np.ones(40)] @ H_TRUE.T
    x2[300:340] = y[:, :2] / y[:, 2:] + np.random.default_rng(5).normal(0, 0.1, (40, 2))
    x1[340:350] = np.c_[np.arange(10.0), 2.0 * np.arange(10.0)]
    x1[350:358] = 7.0
    labels = np.repeat([0, 1, 1, 2, 3, 4, -1], [300, 30, 10, 10, 8, 4, 38])
    want = np.random.default_rng(4).random(400) < 0.7
    good, H_inv = affine_kernel.fit_clusters(x1, x2, labels, want, k=12, max_residual_px=2.0,
                                             iterations=_ITERATIONS, min_neighbours=MIN_NEIGHBOURS)
    fitted = np.zeros(400, bool)
    for lab in range(5):
        rows = np.flatnonzero(labels == lab)
        kk = min(12, rows.size)
        if kk < MIN_NEIGHBOURS:
            continue
        q = rows[want[rows]]
        nb = _brute_neighbours(x1, rows, q, kk)
        g, _, Hi = affine_kernel.fit_rows(x1, x2, q, nb, max_residual_px=2.0,
                                          iterations=_ITERATIONS, min_neighbours=MIN_NEIGHBOURS)
        np.testing.assert_array_equal(good[q], g)
        np.testing.assert_array_equal(H_inv[q[g]], Hi[g])
        fitted[q] = True
    assert not good[~fitted].any()  # unwanted, unlabelled and too-small clusters
    assert good[:300].sum() > 100 and good[300:340].any()
    assert not good[340:358].any()  # collinear and identical points: degenerate


def test_local_affine_pairs_of_rows_are_those_of_all():
    x1, x2 = _matches(300, seed=9)
    labels = np.repeat([0, 1, -1], [200, 70, 30])
    homs = np.stack([np.stack([np.eye(3), np.eye(3) * (1 + c)]) for c in range(2)])
    rng = np.random.default_rng(2)
    rows = np.sort(rng.choice(300, 120, replace=False))
    fit = np.zeros(300, bool)
    fit[rows[::2]] = True
    full = local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0, fit=fit)
    part = local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0, fit=fit, rows=rows)
    np.testing.assert_array_equal(part, full[rows])
    with pytest.raises(ValueError, match="among rows"):
        local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0, fit=fit,
                           rows=rows[1::2])


def test_non_finite_positions_raise():
    x1, x2 = _matches(100, seed=2)
    x1[5] = np.nan
    labels = np.zeros(100, np.int64)
    homs = np.tile(np.eye(3), (1, 2, 1, 1))
    with pytest.raises(ValueError, match="finite"):
        local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0)
    labels[5] = -1  # not in a cluster: never searched
    local_affine_pairs(x1, x2, labels, homs, k=12, max_residual_px=2.0)


def test_warm_loads_the_kernels():
    assert affine_kernel.warm()
    assert affine_kernel.KERNELS.loaded
