"""Point-cloud helpers: PLY round trips, density / outlier figures, distances, pictures."""

from __future__ import annotations

import sys

import numpy as np
import pytest

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


@pytest.mark.parametrize("backend", ["scipy", pytest.param("open3d", marks=needs_open3d)])
def test_cloud_to_cloud_known_shift(backend):
    pts, _ = grid_with_far_outliers()
    grid = pts[:1000]
    shift = np.array([0.02, 0.0, 0.0])  # < half the grid step: nearest point is the shifted twin
    d = pc.cloud_to_cloud(grid, grid + shift, backend=backend)
    for key in ("a_to_b", "b_to_a"):
        assert d[key]["median"] == pytest.approx(0.02, abs=1e-12)
        assert d[key]["p90"] == pytest.approx(0.02, abs=1e-12)
    assert d["chamfer"] == pytest.approx(0.02, abs=1e-12)
    # every other grid point (along z): at distance 0 from the full grid; the other half of the
    # full grid is one step from it
    sub = pc.cloud_to_cloud(grid[::2], grid, backend=backend)
    assert sub["a_to_b"]["p90"] == 0.0
    assert sub["b_to_a"]["mean"] == pytest.approx(SPACING / 2) and sub["b_to_a"]["p90"] == pytest.approx(SPACING)


def test_ply_round_trip_and_reconstruction_export(tmp_path):
    pts, _ = grid_with_far_outliers()
    rgb = (np.arange(len(pts) * 3) % 256).astype(np.uint8).reshape(-1, 3)
    pc.write_ply(pts, tmp_path / "a.ply", rgb)
    xyz, col = pc.read_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(xyz, pts, rtol=1e-7, atol=PLY_ATOL)
    np.testing.assert_array_equal(col, rgb)
    xyz, col = pc.read_ply(pc.write_ply(pts, tmp_path / "b.ply"))
    assert col is None and xyz.shape == pts.shape

    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(num_points3D=50))
    for k, pid in enumerate(sorted(rec.points3D)):
        rec.points3D[pid].color = np.array([k, 2 * k, 255 - k], np.uint8)
    want_xyz, want_rgb = pc.reconstruction_points(rec)
    xyz, col = pc.read_ply(pc.export_ply(rec, tmp_path / "rec.ply"))
    order = np.lexsort(want_xyz.T)  # compare as sets of rows
    got = np.lexsort(xyz.T)
    np.testing.assert_allclose(xyz[got], want_xyz[order], atol=PLY_ATOL)
    np.testing.assert_array_equal(col[got], want_rgb[order])


@needs_open3d
def test_open3d_reads_our_ply(tmp_path):
    import open3d as o3d

    pts, _ = grid_with_far_outliers()
    rgb = np.tile(np.array([[10, 200, 30]], np.uint8), (len(pts), 1))
    cloud = o3d.io.read_point_cloud(str(pc.write_ply(pts, tmp_path / "c.ply", rgb)))
    np.testing.assert_allclose(np.asarray(cloud.points), pts, atol=PLY_ATOL)
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, rgb, atol=1e-6)


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
    assert pc.cloud_to_cloud(pts, pts)["chamfer"] == 0.0
    assert pc.render_cloud_png(pts, None, tmp_path / "x.png") == "matplotlib"


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        pc.cloud_figures(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="backend="):
        pc.cloud_figures(np.zeros((4, 3)), backend="pcl")
    with pytest.raises(ValueError, match="both clouds need points"):
        pc.cloud_to_cloud(np.zeros((0, 3)), np.zeros((3, 3)))
