"""Each pair's own relative rotation (the trust test's evidence): the same whatever the threads
it is estimated on, and right on a synthetic survey with exact ground truth, from the pairs'
stored verified models and from RANSAC where a pair has none."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.geometry import rotation_angle_deg
from colmap_miho.sfm.global_estimate import _pair_rotations
from miho_bench.hinge_scene import make_hinged_survey


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    scene = make_hinged_survey(tmp_path_factory.mktemp("pairs"), wrong_per_right=0.0, seed=2)
    db = ColmapDatabase(scene.database)
    kp = {im.image_id: np.asarray(db.handle.read_keypoints(int(im.image_id))[:, :2], np.float64)
          for im in db.images()}
    cams = {im.image_id: db.handle.read_camera(im.camera_id) for im in db.images()}
    stored = {p: db.verified_model(*p) for p in scene.matches}
    return scene, kp, cams, stored


@pytest.mark.parametrize("threads", [2, -1])
def test_the_rotations_do_not_depend_on_the_threads(survey, threads):
    scene, kp, cams, _ = survey
    one = _pair_rotations(pycolmap, scene.matches, {}, kp, cams, seed=0, num_threads=1)
    many = _pair_rotations(pycolmap, scene.matches, {}, kp, cams, seed=0, num_threads=threads)
    assert len(one) >= 0.9 * len(scene.matches)
    assert one.keys() == many.keys()
    assert all(np.array_equal(one[p], many[p]) for p in one)


@pytest.mark.parametrize("models", ["stored", "ransac", "half"])
def test_the_rotations_are_the_true_relative_rotations(survey, models):
    scene, kp, cams, stored = survey
    assert sum(t is not None for t in stored.values()) >= 0.9 * len(scene.matches)
    given = {"stored": stored, "ransac": {}, "half": {p: t for k, (p, t) in enumerate(sorted(stored.items())) if k % 2}}
    R = {k + 1: r for k, r in enumerate(scene.layout.rotations)}  # image ids follow the flight order
    rot = _pair_rotations(pycolmap, scene.matches, given[models], kp, cams, seed=0, num_threads=2)
    assert len(rot) >= 0.9 * len(scene.matches)
    errors = [rotation_angle_deg(Rij, R[j] @ R[i].T) for (i, j), Rij in rot.items()]
    assert np.median(errors) < 1.0  # (R_i R_j^T, the wrong way round, is 3 deg off here)


@pytest.mark.parametrize("config", ["CALIBRATED", "UNCALIBRATED"])
def test_a_stored_essential_matrix_gives_its_own_rotation(survey, config):
    """A stored CALIBRATED model is posed, not estimated again: an essential matrix turned by 10
    degrees gives that turned rotation. Any other model is estimated again from the matches."""
    scene, kp, cams, _ = survey
    p = sorted(scene.matches)[0]
    one = {p: scene.matches[p]}
    fresh = _pair_rotations(pycolmap, one, {}, kp, cams, seed=0)[p]
    turned = pycolmap.Rotation3d(np.radians([0.0, 0.0, 10.0])).matrix() @ fresh
    E = pycolmap.essential_matrix_from_pose(pycolmap.Rigid3d(pycolmap.Rotation3d(turned), [1.0, 0.0, 0.0]))
    K = [cams[i].calibration_matrix() for i in p]
    model = pycolmap.TwoViewGeometry()
    model.config = getattr(pycolmap.TwoViewGeometryConfiguration, config)
    model.E = E
    model.F = np.linalg.inv(K[1]).T @ E @ np.linalg.inv(K[0])
    own = _pair_rotations(pycolmap, one, {p: model}, kp, cams, seed=0)[p]
    if config == "CALIBRATED":
        assert rotation_angle_deg(own, turned) < 0.1
        assert abs(rotation_angle_deg(own, fresh) - 10.0) < 0.1
    else:
        assert np.array_equal(own, fresh)


def test_a_stored_model_that_cannot_be_posed_is_estimated_again(survey):
    scene, kp, cams, _ = survey
    p = sorted(scene.matches)[0]
    one = {p: scene.matches[p]}
    model = pycolmap.TwoViewGeometry()
    model.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED  # and no E
    assert np.array_equal(_pair_rotations(pycolmap, one, {p: model}, kp, cams, seed=0)[p],
                          _pair_rotations(pycolmap, one, {}, kp, cams, seed=0)[p])
