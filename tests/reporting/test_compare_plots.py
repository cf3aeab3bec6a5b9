"""The comparison figures accept failures, empty inputs and missing pairs."""

from __future__ import annotations

import math

import numpy as np

from colmap_miho.reporting import plots


def test_pose_error_curves_with_failures(tmp_path):
    curves = {"model": {"baseline x": [0.1, 0.3, math.inf], "refined y": [0.2, None, 0.25]},
              "two-view E": {"baseline": [1.0, 30.0]}, "empty": {}}
    p = plots.plot_pose_error_curves(curves, tmp_path / "c.png")
    assert p.read_bytes()[:4] == b"\x89PNG"


def test_displacement_histogram_empty_and_full(tmp_path):
    assert plots.plot_displacement_histogram(np.zeros(0), tmp_path / "e.png").stat().st_size > 1000
    d = np.random.default_rng(0).exponential(0.4, 500)
    assert plots.plot_displacement_histogram(d, tmp_path / "d.png").stat().st_size > 1000


def test_matches_per_pair_missing_after(tmp_path):
    before = {"img_01.png|img_02.png": 120, "img_01.png|img_03.png": 30}
    after = {"img_01.png|img_02.png": 100}
    assert plots.plot_matches_per_pair(before, after, tmp_path / "m.png").stat().st_size > 1000
    assert plots.short_labels(list(before)) == ["1-2", "1-3"]


# names are plain text: an image name with two "$" was parsed as math text and raised
MATH_NAMES = ["a$x$.png|b$y$.png", r"$\notacommand{$.png|c.png", "img_01.png|img_$2$.png"]


def test_image_names_with_dollars_are_plain_text(tmp_path):
    import matplotlib

    before = {name: 10 + k for k, name in enumerate(MATH_NAMES)}
    png = plots.plot_matches_per_pair(before, before, tmp_path / "m.png", title="$x$ in $\\bad{$")
    assert png.stat().st_size > 1000
    curves = {r"$\bad{$": {"baseline $a$": [0.1, 0.2], "refined $\\x{$": [0.3]}}
    assert plots.plot_pose_error_curves(curves, tmp_path / "c.png", title="$_$").read_bytes()[:4] == b"\x89PNG"
    d = np.random.default_rng(0).exponential(0.4, 50)
    assert plots.plot_displacement_histogram(d, tmp_path / "d.png", title="$\\q{$").stat().st_size > 1000
    assert matplotlib.rcParams["text.parse_math"] is True  # the user's own settings are left alone


def test_point_cloud_title_is_plain_text(tmp_path):
    from colmap_miho.reporting.pointcloud import render_cloud_png

    p = np.random.default_rng(1).normal(size=(50, 3))
    render_cloud_png(p, None, tmp_path / "p.png", title="$\\bad{$ name", backend="matplotlib")
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
