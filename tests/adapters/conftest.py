"""Fixtures of the adapter tests: a small rendered scene, a private copy of its database and its GT
model written to a folder."""

from __future__ import annotations

import pytest

from miho_bench.synthetic import make_synthetic_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """4 rendered images, 80 points (one per test module: tests only read it)."""
    return make_synthetic_scene(tmp_path_factory.mktemp("scene"), num_images=4, num_points=80,
                                render_images=True, seed=5)


@pytest.fixture
def db_copy(scene, tmp_path):
    """A private copy of the scene database (tests may lock or replace it)."""
    target = tmp_path / "work" / "scene.db"
    target.parent.mkdir()
    target.write_bytes(scene.database.read_bytes())
    return target


@pytest.fixture
def model(scene, tmp_path):
    """The scene's GT reconstruction written as a COLMAP model folder (binary)."""
    folder = tmp_path / "model"
    folder.mkdir()
    scene.gt_reconstruction.write(str(folder))
    return folder
