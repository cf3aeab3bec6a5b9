"""The aerial-survey scene: short tracks, a sequential + k-nearest pair graph, true matches,
planted outliers and keypoint noise as documented."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from miho_bench.synthetic import make_survey_scene, survey_layout, survey_pairs


def test_survey_tracks_are_short_and_match_the_overlap():
    fo, so = 0.7, 0.4
    lay = survey_layout(80, forward_overlap=fo, side_overlap=so, points_per_image=200, seed=1)
    seen = np.zeros(len(lay.points), int)
    per_image = []
    for k in range(len(lay.centres)):
        idx, xy = lay.project(k)
        assert np.all((xy >= 0) & (xy < (lay.width, lay.height)))
        seen[idx] += 1
        per_image.append(len(idx))
    # interior points (away from the area's border) are seen by ~ 1 / ((1 - fo) (1 - so)) images
    c = lay.centres[:, :2]
    margin = np.array([lay.width, lay.height]) / lay.focal / 2  # half a footprint
    inner = np.all((lay.points[:, :2] > c.min(0) + margin) & (lay.points[:, :2] < c.max(0) - margin), axis=1)
    expected = 1 / ((1 - fo) * (1 - so))
    assert inner.sum() > 500
    assert 0.9 * expected < seen[inner].mean() < 1.1 * expected  # 5.51 measured, seed 1
    assert seen.max() < 3 * expected < len(lay.centres) / 3  # nothing like a point in every image
    assert 180 < np.median(per_image) < 220  # points_per_image=200
    assert lay.lines >= 3


def test_survey_pairs_sequential_and_nearest():
    line = np.column_stack([np.arange(6.0), np.zeros(6), np.ones(6)])
    assert survey_pairs(line, sequential=1, nearest=0) == [(i, i + 1) for i in range(5)]
    assert survey_pairs(line, sequential=2, nearest=0) == sorted({(i, j) for i in range(6) for j in (i + 1, i + 2)
                                                                  if j < 6})
    # a grid: the 4 nearest of an inner node are its 4 axis neighbours, found from either side
    g = np.array([(x, y, 0.0) for y in range(3) for x in range(3)])
    pairs = survey_pairs(g, sequential=0, nearest=4)
    assert {(1, 4), (3, 4), (4, 5), (4, 7)} <= set(pairs)
    assert all(i < j for i, j in pairs) and len(pairs) == len(set(pairs))
    with pytest.raises(ValueError, match="sequential"):
        survey_pairs(line, sequential=-1)


def test_survey_layout_rejects_bad_input():
    with pytest.raises(ValueError, match="forward_overlap"):
        survey_layout(10, forward_overlap=1.0)
    with pytest.raises(ValueError, match="num_images"):
        survey_layout(1)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    return make_survey_scene(tmp_path_factory.mktemp("survey"), num_images=16, points_per_image=120,
                             outlier_ratio=0.25, noise_px=1.0, width=480, height=360, render_images=True, seed=2)


def test_survey_database_matches_and_noise(survey):
    with ColmapDatabase(survey.database) as db:
        assert db.num_images() == 16
        assert db.num_verified_pairs() == len(survey.pairs)
        true_frac, counts = [], []
        for i, j in survey.pairs:
            m = db.matches(i, j, "verified")
            np.testing.assert_array_equal(m, db.matches(i, j, "raw"))
            assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)
            truth = survey.is_true_match(i, j, m)
            assert truth.sum() >= 15  # min_pair_matches
            true_frac.append(truth.mean())
            counts.append(truth.sum())
        kp = db.keypoints(5)
    assert abs(np.mean(true_frac) - 0.75) < 0.03
    # the graph is sparse: far fewer pairs than exhaustive, yet every image is in one
    assert len(survey.pairs) < 16 * 15 / 2 / 2
    assert {i for p in survey.pairs for i in p} == set(range(1, 17))
    err = np.linalg.norm(kp - survey.gt_keypoints[5], axis=1)
    assert abs(np.nanmedian(err) - 1.18) < 0.25  # Gaussian 1 px per axis
    tl = [p.track.length() for p in survey.gt_reconstruction.points3D.values()]
    assert 2 <= np.mean(tl) < 8 and max(tl) < 16


def test_survey_images_show_the_points(survey):
    import cv2

    img = cv2.imread(str(survey.image_dir / "survey_00005.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (360, 480)
    xy = survey.gt_keypoints[6]  # image id 6 = survey_00005.png
    xy = xy[np.isfinite(xy[:, 0])]
    r, c = np.round(xy[:, 1]).astype(int), np.round(xy[:, 0]).astype(int)
    ok = (r >= 0) & (r < 360) & (c >= 0) & (c < 480)
    # the renderer draws a bright peak at every point, the background is black
    assert np.median(img[r[ok], c[ok]]) > 100
    assert np.mean(img == 0) > 0.3


def test_survey_pairs_store_the_true_fundamental_matrix(survey):
    # the camera has no focal prior: an UNCALIBRATED geometry with F, not an empty (degenerate) one
    import pycolmap

    with ColmapDatabase(survey.database) as db:
        for i, j in survey.pairs:
            tvg = db.handle.read_two_view_geometry(i, j)
            assert tvg.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            m = db.matches(i, j, "verified").astype(np.int64)
            true = survey.is_true_match(i, j, m)
            xa = np.column_stack([survey.gt_keypoints[i][m[true, 0]] + 0.5, np.ones(true.sum())])
            xb = np.column_stack([survey.gt_keypoints[j][m[true, 1]] + 0.5, np.ones(true.sum())])
            lines = xa @ tvg.F.T
            dist = np.abs(np.einsum("ij,ij->i", xb, lines)) / np.linalg.norm(lines[:, :2], axis=1)
            assert dist.max() < 1e-6  # true correspondences at their true positions, pixels
