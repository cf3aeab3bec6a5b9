"""Optional extras (demo, plots): a missing one gives one clear line naming the pip command."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.extras import MissingExtraError, require


def _block(monkeypatch, top: str) -> None:
    """Make ``import top`` (and its submodules) fail as if the package were not installed."""
    for name in [m for m in sys.modules if m == top or m.startswith(top + ".")] + [top]:
        monkeypatch.setitem(sys.modules, name, None)


def test_require_returns_the_module():
    assert require("json", "plots", "x").dumps([1]) == "[1]"


@pytest.mark.parametrize(("module", "extra", "package"), [
    ("skimage.data", "demo", "scikit-image"), ("matplotlib.pyplot", "plots", "matplotlib")])
def test_require_names_the_extra(monkeypatch, module, extra, package):
    _block(monkeypatch, module.split(".")[0])
    with pytest.raises(MissingExtraError) as info:
        require(module, extra, "the thing")
    msg = str(info.value)
    assert msg == f"the thing needs {package}, which is not installed: pip install 'colmap-miho[{extra}]'"


def test_library_sites_raise_the_clear_error(monkeypatch, tmp_path):
    from colmap_miho.reporting import demo_scene, plots, pointcloud

    _block(monkeypatch, "skimage")
    with pytest.raises(MissingExtraError, match=r"colmap-miho\[demo\]"):
        demo_scene.build_planes()
    _block(monkeypatch, "matplotlib")
    with pytest.raises(MissingExtraError, match=r"colmap-miho\[plots\]"):
        plots.plot_pose_error_curves({"a": {"rot": [1.0]}}, tmp_path / "c.png")
    pts = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(MissingExtraError, match=r"colmap-miho\[plots\]"):
        pointcloud.render_cloud_png(pts, None, tmp_path / "p.png", backend="matplotlib")


@pytest.mark.parametrize(("blocked", "argv", "extra"), [
    ("skimage", ["demo", "--output", "OUT"], "demo"),
    ("matplotlib", ["demo", "--output", "OUT"], "demo"),
    ("matplotlib", ["compare", "--database", "d.db", "--images", "i", "--output", "OUT"], "plots"),
    ("matplotlib", ["run", "--images", "i", "--output", "OUT", "--compare"], "plots"),
])
def test_cli_fails_early_with_one_line(monkeypatch, capsys, tmp_path, blocked, argv, extra):
    _block(monkeypatch, blocked)
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.endswith(f"pip install 'colmap-miho[{extra}]'")
    assert not (tmp_path / "out").exists()  # failed before any work
