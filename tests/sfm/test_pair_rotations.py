"""Each pair's own relative rotation (the trust test's evidence): the same whatever the threads
it is estimated on, and right on a synthetic survey with exact ground truth."""

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
    return scene, kp, cams


@pytest.mark.parametrize("threads", [2, -1])
def test_the_rotations_do_not_depend_on_the_threads(survey, threads):
    scene, kp, cams = survey
    one = _pair_rotations(pycolmap, scene.matches, kp, cams, seed=0, num_threads=1)
    many = _pair_rotations(pycolmap, scene.matches, kp, cams, seed=0, num_threads=threads)
    assert len(one) >= 0.9 * len(scene.matches)
    assert one.keys() == many.keys()
    assert all(np.array_equal(one[p], many[p]) for p in one)


def test_the_rotations_are_the_true_relative_rotations(survey):
    scene, kp, cams = survey
    R = {k + 1: r for k, r in enumerate(scene.layout.rotations)}  # image ids follow the flight order
    rot = _pair_rotations(pycolmap, scene.matches, kp, cams, seed=0, num_threads=2)
    errors = [rotation_angle_deg(Rij, R[j] @ R[i].T) for (i, j), Rij in rot.items()]
    assert np.median(errors) < 1.0  # (R_i R_j^T, the wrong way round, is 3 deg off here)
