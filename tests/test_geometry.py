"""Two-view geometry (:mod:`colmap_miho.geometry`): the fundamental matrix fit, Sampson
distances, the RANSAC bound and the epipolar transfer into a third view, on synthetic cameras."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from doppelganger import FOCAL, HEIGHT, WIDTH

from colmap_miho import geometry
from colmap_miho.geometry import fit_fundamental, hypotheses_needed, sampson_sq, transfer

#: Sampson distance (px) of noise-free correspondences under the fitted F.
F_FIT_TOL_PX = 0.05
#: Relative difference of batched and one-at-a-time Sampson distances (rounding only).
SAMPSON_BATCH_RTOL = 1e-9
#: Share of the outlier correspondences the fit may still count as inliers.
MAX_OUTLIER_INLIER_SHARE = 0.05
#: Epipolar transfer error (px) into a third view with noise-free points and exact F.
TRANSFER_TOL_PX = 1e-6


def _camera(c, yaw_deg):
    a = np.deg2rad(yaw_deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
    return K, R, -R @ np.asarray(c, float)


def _project(cam, X):
    K, R, t = cam
    x = (X @ R.T + t) @ K.T
    return x[:, :2] / x[:, 2:]


def _f_from(cam1, cam2):
    (K1, R1, t1), (K2, R2, t2) = cam1, cam2
    R = R2 @ R1.T
    t = t2 - R @ t1
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)


def _three_views():
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-4, 4, 200), rng.uniform(-3, 3, 200), rng.uniform(8, 14, 200)])
    cams = [_camera([0, 0, 0], 0), _camera([2, 0.3, 0.5], -6), _camera([0.8, 2.5, -0.5], 3)]
    return X, cams


def test_fit_fundamental_matches_the_true_geometry():
    X, cams = _three_views()
    x1, x2 = _project(cams[0], X), _project(cams[1], X)
    F = fit_fundamental(x1, x2, np.random.default_rng(0))
    assert F is not None
    assert np.sqrt(sampson_sq(F, x1, x2)).max() < F_FIT_TOL_PX
    assert fit_fundamental(x1[:7], x2[:7], np.random.default_rng(0)) is None


def test_sampson_batched_equals_one_at_a_time():
    X, cams = _three_views()
    x1, x2 = _project(cams[0], X), _project(cams[1], X) + np.random.default_rng(1).normal(0, 2, (len(X), 2))
    Fs = np.random.default_rng(2).normal(size=(2, 5, 3, 3))
    batched = sampson_sq(Fs, x1, x2)
    assert batched.shape == (2, 5, len(X))
    assert sampson_sq(Fs[0, 0], x1, x2).shape == (len(X),)
    for a, b in itertools.product(range(2), range(5)):
        F = Fs[a, b]
        h1, h2 = np.column_stack([x1, np.ones(len(X))]), np.column_stack([x2, np.ones(len(X))])
        l2, l1 = h1 @ F.T, h2 @ F  # x1's lines in image 2, x2's in image 1
        ref = np.sum(h2 * l2, 1) ** 2 / (l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2)
        np.testing.assert_allclose(batched[a, b], ref, rtol=SAMPSON_BATCH_RTOL)


def test_hypotheses_needed_is_the_ransac_bound():
    assert hypotheses_needed(1.0, 0.999) == 1.0
    assert hypotheses_needed(0.0, 0.999) == np.inf
    assert hypotheses_needed(0.5, 0.99) == pytest.approx(np.log(0.01) / np.log(1 - 0.5**8))
    assert hypotheses_needed(0.9, 0.999) < hypotheses_needed(0.8, 0.999) < hypotheses_needed(0.8, 0.9999)


def _count_solves(monkeypatch):
    calls = []
    solve = geometry._solve

    def counting(h1, h2):
        calls.append(h1.shape[0])
        return solve(h1, h2)

    monkeypatch.setattr(geometry, "_solve", counting)
    return calls


def test_fit_stops_after_one_batch_on_clean_matches(monkeypatch):
    X, cams = _three_views()
    x1, x2 = _project(cams[0], X), _project(cams[1], X)
    calls = _count_solves(monkeypatch)
    F = fit_fundamental(x1, x2, np.random.default_rng(0), batch=16)
    assert F is not None and np.sqrt(sampson_sq(F, x1, x2)).max() < F_FIT_TOL_PX
    assert calls == [16, 1, 1]  # one batch of hypotheses, then the two refits


def test_fit_scores_more_batches_with_outliers(monkeypatch):
    """A third of the matches are outliers: 0.67^8 ~ 4% of the samples are clean, so the bound
    asks for more hypotheses than one batch holds; the fit still finds the geometry."""
    X, cams = _three_views()
    rng = np.random.default_rng(5)
    x1, x2 = _project(cams[0], X), _project(cams[1], X)
    bad = rng.random(len(X)) < 1 / 3
    x2[bad] = rng.uniform(0, [WIDTH, HEIGHT], (int(bad.sum()), 2))
    calls = _count_solves(monkeypatch)
    F = fit_fundamental(x1, x2, np.random.default_rng(0), batch=16)
    assert F is not None
    assert len(calls) > 3 and sum(calls[:-2]) <= 128
    d = np.sqrt(sampson_sq(F, x1, x2))
    assert d[~bad].max() < F_FIT_TOL_PX
    assert np.mean(d[bad] < 1.5) < MAX_OUTLIER_INLIER_SHARE


def test_transfer_lands_on_the_third_projection():
    X, cams = _three_views()
    x1, x2, x3 = (_project(c, X) for c in cams)
    pts, sin = transfer(_f_from(cams[0], cams[2]), _f_from(cams[1], cams[2]), x1, x2)
    good = sin > np.sin(np.deg2rad(5))
    assert good.mean() > 0.5  # non-collinear centres: most lines meet at a clear angle
    assert np.abs(pts[good] - x3[good]).max() < TRANSFER_TOL_PX


def test_transfer_equals_the_cross_product_of_the_lines():
    rng = np.random.default_rng(4)
    F1, F2 = rng.normal(size=(2, 3, 3))
    x1, x2 = rng.uniform(0, 1000, (2, 50, 2))
    pts, _ = transfer(F1, F2, x1, x2)
    p = np.cross(np.column_stack([x1, np.ones(50)]) @ F1.T, np.column_stack([x2, np.ones(50)]) @ F2.T)
    np.testing.assert_array_equal(pts, p[:, :2] / p[:, 2:])
