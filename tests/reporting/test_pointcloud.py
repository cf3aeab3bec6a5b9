"""Point clouds: the PLY export, density / outlier figures, pictures."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from helpers.ply import read_ply, write_ply

from colmap_miho.reporting import pointcloud as pc

SPACING = 0.1  # grid step of the synthetic cloud, in cloud units
NUM_FAR = 20  # planted far outliers
# PLY stores float32: coordinates of order 1 come back within this (float32 epsilon ~1.2e-7)
PLY_ATOL = 1e-6

needs_open3d = pytest.mark.skipif(not pc.have_open3d(), reason="open3d not installed (optional extra 'pointcloud')")


def grid_with_far_outliers(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 10 x 10 x 10 grid with step SPACING plus NUM_FAR points 50-100 units away."""
    g = np.arange(10) * SPACING
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(NUM_FAR, 3))
    far = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(50, 100, size=(NUM_FAR, 1))
    pts = np.concatenate([grid, far])
    planted = np.zeros(len(pts), bool)
    planted[len(grid):] = True
    return pts, planted


@pytest.mark.parametrize("backend", ["scipy", pytest.param("open3d", marks=needs_open3d)])
def test_cloud_figures_grid_spacing_and_planted_outliers(backend):
    pts, planted = grid_with_far_outliers()
    fig = pc.cloud_figures(pts, backend=backend)
    assert fig["backend"] == backend and fig["num_points"] == len(pts)
    np.testing.assert_array_equal(pc.statistical_outliers(pts, backend=backend), planted)
    assert fig["outlier_share"] == pytest.approx(NUM_FAR / len(pts))
    assert fig["spacing_median"] == pytest.approx(SPACING, rel=1e-9)  # grid points' nearest neighbour
    assert fig["spacing_mean"] > SPACING  # the far points pull the mean up


@needs_open3d
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scipy_outlier_rule_equals_open3d(seed):
    # anisotropic Gaussian: many borderline points, so the exact rule (self included, ddof) matters
    pts = np.random.default_rng(seed).normal(size=(3000, 3)) * [1.0, 2.0, 0.5]
    a = pc.statistical_outliers(pts, backend="scipy")
    b = pc.statistical_outliers(pts, backend="open3d")
    assert 50 < a.sum() < 300
    np.testing.assert_array_equal(a, b)


def test_ply_round_trip_and_reconstruction_export(tmp_path):
    pts, _ = grid_with_far_outliers()
    rgb = (np.arange(len(pts) * 3) % 256).astype(np.uint8).reshape(-1, 3)
    write_ply(pts, tmp_path / "a.ply", rgb)
    xyz, col = read_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(xyz, pts, rtol=1e-7, atol=PLY_ATOL)
    np.testing.assert_array_equal(col, rgb)
    xyz, col = read_ply(write_ply(pts, tmp_path / "b.ply"))
    assert col is None and xyz.shape == pts.shape

    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(num_points3D=50))
    for k, pid in enumerate(sorted(rec.points3D)):
        rec.points3D[pid].color = np.array([k, 2 * k, 255 - k], np.uint8)
    want_xyz, want_rgb = pc.reconstruction_points(rec)
    xyz, col = read_ply(pc.export_ply(rec, tmp_path / "rec.ply"))
    order = np.lexsort(want_xyz.T)  # compare as sets of rows
    got = np.lexsort(xyz.T)
    np.testing.assert_allclose(xyz[got], want_xyz[order], atol=PLY_ATOL)
    np.testing.assert_array_equal(col[got], want_rgb[order])


def test_render_png(tmp_path):
    import cv2

    pts, _ = grid_with_far_outliers()
    backend = pc.render_cloud_png(pts, None, tmp_path / "m.png", width=400, height=300, backend="matplotlib")
    assert backend == "matplotlib"
    img = cv2.imread(str(tmp_path / "m.png"))
    assert img.shape == (300, 400, 3) and img.std() > 5  # something was drawn
    used = pc.render_cloud_png(pts, np.full((len(pts), 3), 128, np.uint8), tmp_path / "a.png", width=320, height=240)
    assert used in ("open3d", "matplotlib") and cv2.imread(str(tmp_path / "a.png")).shape == (240, 320, 3)


def test_without_open3d_clear_error_and_numpy_fallbacks(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d -> ImportError
    assert not pc.have_open3d()
    with pytest.raises(RuntimeError, match=r"open3d is not installed: pip install 'colmap-miho\[pointcloud\]'"):
        pc.cloud_figures(np.zeros((5, 3)), backend="open3d")
    pts, planted = grid_with_far_outliers()
    assert pc.cloud_figures(pts)["backend"] == "scipy"
    assert pc.render_cloud_png(pts, None, tmp_path / "x.png") == "matplotlib"


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        pc.cloud_figures(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="backend="):
        pc.cloud_figures(np.zeros((4, 3)), backend="pcl")
