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
    assert plots._short_labels(list(before)) == ["1-2", "1-3"]
