"""The GT oracle filter on a synthetic scene with planted wrong matches (pycolmap.synthesize_dataset).

The planted outliers are known from the synthetic reconstruction (two keypoints that are not
observations of one 3D point); their GT epipolar distance is computed here independently of
the module (COLMAP coordinates straight from the reconstruction, no half-pixel conversion), so
the test checks that the oracle removes exactly the planted outliers beyond the threshold.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")

from colmap_miho.adapters.database import ColmapDatabase  # noqa: E402
from colmap_miho.reporting.gt_model import poses_from_reconstruction  # noqa: E402
from miho_bench import oracle  # noqa: E402

THRESHOLD = oracle.ORACLE_THRESHOLD_PX


def _synthetic(path, inlier_ratio=0.6):
    """A database whose stored inliers are all raw matches (planted outliers included), and its
    noise-free GT reconstruction."""
    opts = pycolmap.SyntheticDatasetOptions(
        num_rigs=1, num_frames_per_rig=5, num_points3D=120, inlier_match_ratio=inlier_ratio,
        camera_model_id=pycolmap.CameraModelId.PINHOLE, camera_params=[1280.0, 1280.0, 512.0, 384.0])
    with ColmapDatabase.create(path) as db:
        gt = db.synthesize(opts)
        db.store_raw_matches_as_inliers()
    return gt


def _colmap_F(rec, i, j):
    """GT F in COLMAP coordinates (x2^T F x1 = 0), from the reconstruction alone."""
    K1 = np.asarray(rec.cameras[rec.images[i].camera_id].calibration_matrix())
    K2 = np.asarray(rec.cameras[rec.images[j].camera_id].calibration_matrix())
    p1, p2 = rec.images[i].cam_from_world(), rec.images[j].cam_from_world()
    R1, t1 = np.asarray(p1.rotation.matrix()), np.asarray(p1.translation)
    R2, t2 = np.asarray(p2.rotation.matrix()), np.asarray(p2.translation)
    R = R2 @ R1.T
    t = t2 - R @ t1
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)


def _expected(rec, db_path):
    """(pair -> stored matches, pair -> bool planted outlier, pair -> symmetric distance)."""
    stored, planted, dist = {}, {}, {}
    with ColmapDatabase(db_path) as db:
        for pr in db.pairs("verified"):
            i, j = pr.image_id1, pr.image_id2
            m = db.matches(i, j, "verified").astype(np.int64)
            im1, im2 = rec.images[i], rec.images[j]
            p3d1 = np.array([im1.points2D[k].point3D_id if im1.points2D[k].has_point3D() else -1 for k in m[:, 0]])
            p3d2 = np.array([im2.points2D[k].point3D_id if im2.points2D[k].has_point3D() else -2 for k in m[:, 1]])
            x1 = np.array([im1.points2D[k].xy for k in m[:, 0]])
            x2 = np.array([im2.points2D[k].xy for k in m[:, 1]])
            F = _colmap_F(rec, i, j)
            h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
            l2, l1 = h1 @ F.T, h2 @ F
            alg = np.abs(np.sum(h2 * l2, 1))
            dist[(i, j)] = 0.5 * (alg / np.hypot(*l2[:, :2].T) + alg / np.hypot(*l1[:, :2].T))
            stored[(i, j)] = m
            planted[(i, j)] = p3d1 != p3d2
    return stored, planted, dist


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_oracle_removes_exactly_the_planted_outliers_beyond_the_threshold(tmp_path):
    src = tmp_path / "in.db"
    rec = _synthetic(src)
    stored, planted, dist = _expected(rec, src)
    n_planted = sum(int(p.sum()) for p in planted.values())
    assert n_planted > 50  # the scene really has outliers in its stored inliers
    # the planted inliers are exact, so they all lie on their epipolar lines
    assert max(float(d[~planted[k]].max()) for k, d in dist.items()) < 1e-3
    want_removed = {k: planted[k] & (dist[k] > THRESHOLD) for k in stored}
    before = _digest(src)

    out = tmp_path / "oracle.db"
    stats = oracle.write_oracle_database(src, out, poses_from_reconstruction(rec))

    assert _digest(src) == before  # the input is never changed
    assert stats.num_matches_removed == sum(int(w.sum()) for w in want_removed.values())
    assert stats.num_pairs_without_gt == 0
    with ColmapDatabase(out) as db:
        for (i, j), m in stored.items():
            want = m[~want_removed[(i, j)]]
            got_inliers = db.matches(i, j, "verified").astype(np.int64)
            np.testing.assert_array_equal(got_inliers, want)
            if want_removed[(i, j)].any():  # changed pairs: the matches row mirrors the inliers
                np.testing.assert_array_equal(db.matches(i, j, "raw").astype(np.int64), want)
    # a planted outlier close to its line (by chance) stays: only the distance decides
    kept_planted = sum(int((planted[k] & ~want_removed[k]).sum()) for k in stored)
    assert stats.num_matches_in - stats.num_matches_removed == sum(len(m) for m in stored.values()) - sum(
        int(w.sum()) for w in want_removed.values())
    assert kept_planted == sum(int((planted[k] & (dist[k] <= THRESHOLD)).sum()) for k in stored)


def test_counts_agree_with_the_oracle_and_an_image_outside_the_gt_is_left_alone(tmp_path):
    src = tmp_path / "in.db"
    rec = _synthetic(src)
    gt = poses_from_reconstruction(rec)
    _, planted, dist = _expected(rec, src)
    dropped = sorted(gt)[0]
    partial = {k: v for k, v in gt.items() if k != dropped}

    from colmap_miho.reporting.report import read_database_inliers

    inl = read_database_inliers(src)
    counts = oracle.outlier_counts(oracle.gt_epipolar_distances(inl.keypoints, inl.matches, gt))
    want_out = sum(int((planted[k] & (dist[k] > THRESHOLD)).sum()) for k in dist)
    assert counts.num_outliers == want_out
    assert counts.num_correct == counts.num_matches - want_out
    assert counts.num_pairs == len(dist) == counts.num_correct_pairs  # 60% inliers: every median is on the line

    stats = oracle.write_oracle_database(src, tmp_path / "partial.db", partial)
    n_images = len(gt)
    assert stats.num_pairs_without_gt == n_images - 1  # the pairs of the dropped image
    after = read_database_inliers(tmp_path / "partial.db")
    pairs_dropped = [k for k in inl.matches if dropped in k]
    for k in pairs_dropped:
        np.testing.assert_array_equal(after.matches[k], inl.matches[k])
    counts_after = oracle.outlier_counts(oracle.gt_epipolar_distances(after.keypoints, after.matches, partial))
    assert counts_after.num_outliers == 0
    assert counts_after.num_correct == oracle.outlier_counts(
        oracle.gt_epipolar_distances(inl.keypoints, inl.matches, partial)).num_correct


def test_outlier_counts_by_hand():
    d = {("a", "b"): np.array([0.1, 5.0, 3.9, np.nan]),  # median 4.45 by inf-NaN: not a correct pair
         ("a", "c"): np.array([0.5, 0.7, 9.0]),
         ("b", "c"): np.zeros(0)}
    c = oracle.outlier_counts(d, 4.0)
    assert (c.num_pairs, c.num_matches, c.num_correct, c.num_outliers) == (2, 7, 4, 3)
    assert c.outlier_share == pytest.approx(3 / 7)
    assert (c.num_correct_pairs, c.correct_pair_matches, c.correct_pair_outliers) == (1, 3, 1)
    with pytest.raises(ValueError):
        oracle.outlier_counts(d, 0.0)


def test_output_must_not_exist(tmp_path):
    src = tmp_path / "in.db"
    rec = _synthetic(src, inlier_ratio=1.0)
    (tmp_path / "o.db").write_bytes(b"")
    with pytest.raises(FileExistsError):
        oracle.write_oracle_database(src, tmp_path / "o.db", poses_from_reconstruction(rec))
