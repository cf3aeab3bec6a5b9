"""GT converters and COLMAP model round trip (synthetic, then the shipped datasets)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.reporting import gt_model as gm
from colmap_miho.reporting.pose_metrics import rotation_error_deg

# The shipped gt_model files print 12 significant digits: agreement to 1e-6 is exact here.
ROT_TOL_DEG = 1e-6
POS_TOL = 1e-6
K_TOL_PX = 1e-6


def _random_poses(n=4, seed=0):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 319.5], [0, 510.0, 239.5], [0, 0, 1]])
    return {
        f"img{i:02d}.png": gm.CameraPose(
            name=f"img{i:02d}.png", K=K, R=Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix(),
            t=rng.normal(size=3), width=640, height=480,
        )
        for i in range(n)
    }


def _assert_same(a, b, k_tol=K_TOL_PX):
    assert sorted(a) == sorted(b)
    for name in a:
        assert rotation_error_deg(a[name].R, b[name].R) < ROT_TOL_DEG, name
        np.testing.assert_allclose(a[name].center, b[name].center, atol=POS_TOL * max(1, np.abs(a[name].center).max()))
        np.testing.assert_allclose(a[name].K, b[name].K, atol=k_tol)
        assert (a[name].width, a[name].height) == (b[name].width, b[name].height)


def test_write_and_load_roundtrip(tmp_path):
    poses = _random_poses()
    gm.write_colmap_model(poses, tmp_path / "m")
    back = gm.load_gt_poses(tmp_path / "m")
    _assert_same(poses, back)
    # COLMAP convention on disk: principal point + 0.5
    assert "320 240" in (tmp_path / "m" / "cameras.txt").read_text()
    # a dataset folder holding gt_model/ is accepted too
    (tmp_path / "ds").mkdir()
    gm.write_colmap_model(poses, tmp_path / "ds" / "gt_model")
    assert sorted(gm.load_gt_poses(tmp_path / "ds")) == sorted(poses)


def test_bad_inputs(tmp_path):
    with pytest.raises(FileNotFoundError):
        gm.load_gt_poses(tmp_path / "missing")
    with pytest.raises(ValueError, match="not a COLMAP model"):
        gm.load_gt_poses(tmp_path)
    bad = tmp_path / "x.camera"
    bad.write_text("1 2 3\n")
    with pytest.raises(ValueError, match="Strecha"):
        gm.read_strecha_camera(bad)
    with pytest.raises(ValueError, match="format"):
        gm.convert_gt("bundler", tmp_path, tmp_path, tmp_path / "o")


@pytest.mark.parametrize("scene", ["strecha_fountain_p11", "strecha_entry_p10"])
def test_strecha_converter_matches_shipped_model(shared_data, tmp_path, scene):
    root = shared_data / scene
    rc = main(["gt", "--format", "strecha", "--input", str(root / "gt_half_res"), "--images",
               str(root / "images"), "--output", str(tmp_path / "gt"), "-q"])
    assert rc == 0
    _assert_same(gm.load_gt_poses(tmp_path / "gt"), gm.load_gt_poses(root / "gt_model"))


def test_strecha_full_res_gt_is_rescaled(shared_data):
    root = shared_data / "strecha_fountain_p11"
    full = gm.strecha_poses(root / "gt_full_res", root / "images")
    half = gm.load_gt_poses(root / "gt_model")
    # the shipped half-res K halves cx directly; the pixel-centre rescale differs by 0.25 px
    _assert_same(full, half, k_tol=0.25 + 1e-6)


def test_middlebury_converter_matches_shipped_model(shared_data, tmp_path):
    root = shared_data / "middlebury_temple_sparse_ring"
    rc = main(["gt", "--format", "middlebury", "--input", str(root / "gt"), "--images",
               str(root / "images"), "--output", str(tmp_path / "gt"), "-q"])
    assert rc == 0
    _assert_same(gm.load_gt_poses(tmp_path / "gt"), gm.load_gt_poses(root / "gt_model"))
