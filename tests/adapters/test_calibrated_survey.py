"""The calibrated survey: COLMAP's stored geometry (CALIBRATED, E, F, verified inliers) agrees
with the true poses, match ends per image are those of a real 8192-SIFT scene, the wrong matches
are what the docstring promises, and the pair graphs have their degree and loop closures."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from miho_bench.calibrated_survey import (
    graph_pairs,
    line_distance_px,
    make_calibrated_survey,
    sampson_px,
)

EPIPOLAR_TOL_PX = 1e-6  # true correspondences at their true positions: on the line up to rounding
VERIFY_PX = 4.0  # make_calibrated_survey's default verify_px


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    return make_calibrated_survey(tmp_path_factory.mktemp("calibrated"), num_images=30, graph="sequential",
                                  neighbours=6, loop_period=5, loop_images=3, render_images=False, seed=3)


def _colmap_gt(survey, image_id):
    """The true keypoint positions of one image in COLMAP coordinates (the database's)."""
    return survey.gt_keypoints[image_id] + 0.5


def test_the_stored_geometry_is_the_true_one(survey):
    lay = survey.layout
    K = lay.intrinsics()
    with ColmapDatabase(survey.database) as db:
        cams = db.handle.read_all_cameras()
        assert len(cams) == 1 and cams[0].model.name == "SIMPLE_PINHOLE" and cams[0].has_prior_focal_length
        np.testing.assert_allclose(cams[0].params, [lay.focal, lay.width / 2, lay.height / 2])
        for i, j in survey.pairs[::7]:
            tvg = db.handle.read_two_view_geometry(i, j)
            assert tvg.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            a, b = i - 1, j - 1
            # E = [t]x R of the true relative pose (unit baseline), F = K^-T E K^-1 (up to scale)
            Ra, Rb = lay.rotations[a], lay.rotations[b]
            t = Rb @ (lay.centres[a] - lay.centres[b])
            R, t = Rb @ Ra.T, t / np.linalg.norm(t)
            tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            np.testing.assert_allclose(tvg.E, tx @ R, atol=1e-9)
            assert np.linalg.matrix_rank(tvg.E, tol=1e-9) == 2
            Fk = np.linalg.inv(K).T @ tvg.E @ np.linalg.inv(K)
            np.testing.assert_allclose(Fk / np.linalg.norm(Fk), tvg.F / np.linalg.norm(tvg.F), atol=1e-9)
            # the true correspondences lie on the epipolar lines (true positions)
            inl = np.asarray(tvg.inlier_matches, np.int64)
            true = survey.is_true_match(i, j, inl)
            xa, xb = _colmap_gt(survey, i)[inl[true, 0]], _colmap_gt(survey, j)[inl[true, 1]]
            assert np.max(sampson_px(tvg.F, xa, xb)) < EPIPOLAR_TOL_PX
            # the stored inliers pass COLMAP's check on the stored (noisy) keypoints; the raw
            # matches hold them and the ones that failed it
            kp_a, kp_b = db.keypoints(i) + 0.5, db.keypoints(j) + 0.5
            assert np.max(sampson_px(tvg.F, kp_a[inl[:, 0]], kp_b[inl[:, 1]])) < VERIFY_PX
            raw = db.matches(i, j, "raw").astype(np.int64)
            rejected = raw[~(raw[:, None, :] == inl[None, :, :]).all(2).any(1)]
            assert len(raw) > len(inl) and len(rejected) == len(raw) - len(inl)
            assert np.min(sampson_px(tvg.F, kp_a[rejected[:, 0]], kp_b[rejected[:, 1]])) >= VERIFY_PX


def test_wrong_matches_random_and_repeated(survey):
    wrong_share, near_line = [], []
    with ColmapDatabase(survey.database) as db:
        for i, j in survey.pairs:
            inl = db.matches(i, j, "verified").astype(np.int64)
            true = survey.is_true_match(i, j, inl)
            wrong_share.append(1 - true.mean())
            F = db.handle.read_two_view_geometry(i, j).F
            w = inl[~true]
            xa, xb = _colmap_gt(survey, i)[w[:, 0]], _colmap_gt(survey, j)[w[:, 1]]
            ok = np.isfinite(xb[:, 0]) & np.isfinite(xa[:, 0])  # a random one may end on an extra keypoint
            d = np.abs(np.diagonal(line_distance_px(F, xa[ok], xb[ok]))) if ok.any() else np.zeros(0)
            near_line.extend(d.tolist())
            assert len(np.unique(inl[:, 1])) == len(inl) and len(np.unique(inl[:, 0])) == len(inl)
    # repeated structure (5% of the true ones, within 1.5 px of the true line) survives
    # verification, random wrong matches mostly not: 3-7% wrong among the verified matches
    assert 0.03 < np.mean(wrong_share) < 0.07
    assert np.median(near_line) < 1.5


def test_match_ends_per_image_as_in_a_real_sift_scene(tmp_path):
    sc = make_calibrated_survey(tmp_path, num_images=60, graph="retrieval", render_images=False, seed=1)
    ends = np.zeros(61)
    with ColmapDatabase(sc.database) as db:
        for p in db.pairs("verified"):
            ends[[p.image_id1, p.image_id2]] += p.num_matches
    assert 8000 < np.median(ends[1:]) < 28000  # real 8192-SIFT scenes: 8,000-28,000
    assert ends[1:].min() > 2000  # the track sample budget is reached nearly everywhere


def test_pair_graphs_degree_and_loop_closures(survey):
    n = 30
    seq = set(survey.candidate_pairs)
    # the sequential window (6 next images), where the images overlap
    assert {(i, i + 1) for i in range(n - 1)} <= seq
    loops = survey.loop_pairs
    assert loops and set(loops) <= seq
    assert all(abs(j - i) > 6 for i, j in loops)
    assert {i if i % 5 == 0 else j for i, j in loops} <= set(range(0, n, 5))
    # retrieval: every image with its k most overlapping; exhaustive: every overlapping pair
    ov = np.array([[0, 50, 40, 0], [50, 0, 30, 20], [40, 30, 0, 10], [0, 20, 10, 0]])
    ret, no_loops = graph_pairs(ov, "retrieval", neighbours=1, min_shared=15)
    assert ret == [(0, 1), (0, 2), (1, 3)] and no_loops == []  # 2's best is 0, 3's is 1
    ret2, _ = graph_pairs(ov, "retrieval", neighbours=2, min_shared=15)
    assert ret2 == [(0, 1), (0, 2), (1, 2), (1, 3)]
    ex, _ = graph_pairs(ov, "exhaustive", min_shared=15)
    assert ex == [(0, 1), (0, 2), (1, 2), (1, 3)]
    with pytest.raises(ValueError, match="graph"):
        graph_pairs(ov, "vocab")
