"""The database layer: half-pixel conversion in one place, round trips, validation, images."""

from __future__ import annotations

import logging
import sqlite3

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_miho.adapters.conventions import HALF_PIXEL, colmap_to_pixel_centre, pixel_centre_to_colmap
from colmap_miho.adapters.database import ColmapDatabase, fitted_geometry, keep_or_fit, validate_database
from colmap_miho.adapters.images import ImageLoader, read_gray_float
from colmap_miho.errors import DatabaseError
from miho_bench.synthetic import make_synthetic_scene

# The synthetic scene's keypoint noise is Gaussian with this sigma per axis; the median 2D
# error of Gaussian noise is sigma * sqrt(2 ln 2) ~ 1.18 sigma (measured 1.11 on seed 0).
NOISE_PX = 1.0
MEDIAN_NOISE_TOL = 0.25


@pytest.fixture(scope="module")
def scene_db(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("scene"), num_images=3, num_points=60,
                                noise_px=NOISE_PX, render_images=False, seed=3)


def _copy(src, dst):
    dst.write_bytes(src.read_bytes())
    return dst


def test_half_pixel_helpers_are_inverse():
    xy = np.array([[0.0, 0.0], [10.25, 3.5]])
    np.testing.assert_array_equal(colmap_to_pixel_centre(xy), xy - HALF_PIXEL)
    np.testing.assert_array_equal(pixel_centre_to_colmap(colmap_to_pixel_centre(xy)), xy)


def test_synthetic_scene_ground_truth(scene_db):
    with ColmapDatabase(scene_db.database) as db:
        kp = db.keypoints(1)
        raw = db.raw_keypoints(1)
        m = db.matches(1, 2, "verified")
        raw_m = db.matches(1, 2, "raw")
    assert raw.shape[1] == 6 and raw.dtype == np.float32
    np.testing.assert_array_equal(kp, raw[:, :2].astype(np.float64) - 0.5)
    err = np.linalg.norm(kp - scene_db.gt_keypoints[1], axis=1)
    assert abs(np.nanmedian(err) - 1.18 * NOISE_PX) < MEDIAN_NOISE_TOL
    # outliers planted in the verified inliers too (outliers_in_verified=True)
    np.testing.assert_array_equal(m, raw_m)
    truth = scene_db.is_true_match(1, 2, m)
    assert 0.05 < 1 - truth.mean() < 0.35


@pytest.mark.parametrize("columns", [2, 4, 6])
def test_keypoint_round_trip_keeps_columns_and_unmoved_rows(tmp_path, columns):
    scene = make_synthetic_scene(tmp_path / "s", num_images=2, num_points=30, keypoint_columns=columns,
                                 render_images=False, seed=1)
    with ColmapDatabase(scene.database) as db:
        before = db.raw_keypoints(1)
        xy = db.keypoints(1)
        assert before.shape[1] == columns
        moved = np.zeros(len(xy), bool)
        moved[[0, 5]] = True
        xy_new = xy.copy()
        xy_new[moved] += [[0.25, -0.75], [1.0, 2.0]]
        # an unmoved row whose value changed must not be written
        xy_new[1] += 3.0
        assert db.write_keypoints(1, xy_new, moved) == 2
    with ColmapDatabase(scene.database) as db:
        after = db.raw_keypoints(1)
    assert after.shape == before.shape and after.dtype == np.float32
    # untouched rows and all affine columns: bit-identical
    np.testing.assert_array_equal(after[~moved], before[~moved])
    np.testing.assert_array_equal(after[:, 2:], before[:, 2:])
    # moved rows: exactly one +0.5 (COLMAP = pixel centre + 0.5)
    np.testing.assert_array_equal(after[moved, :2], (xy_new[moved] + 0.5).astype(np.float32))


def test_write_keypoints_checks_shapes(scene_db, tmp_path):
    db_path = _copy(scene_db.database, tmp_path / "c.db")
    with ColmapDatabase(db_path) as db:
        n = len(db.keypoints(1))
        with pytest.raises(ValueError, match="xy must be"):
            db.write_keypoints(1, np.zeros((n + 1, 2)), np.ones(n + 1, bool))


def test_keep_or_fit_keeps_a_verified_model_else_fits(scene_db, tmp_path):
    db_path = _copy(scene_db.database, tmp_path / "k.db")
    fitted = []

    def fit():
        fitted.append(1)
        return fitted_geometry(None, np.eye(3))

    with ColmapDatabase(db_path) as db:
        h, m = db.handle, db.matches(1, 2, "verified")[:10]
        stored = h.read_two_view_geometry(1, 2)
        kept = keep_or_fit(h, 1, 2, m, fit)
        assert not fitted and int(kept.config) == int(stored.config)  # the verified model, not fitted
        np.testing.assert_array_equal(kept.F, stored.F)
        np.testing.assert_array_equal(kept.inlier_matches, m)
        refit = keep_or_fit(h, 1, 2, m, fit, keep=False)
        assert fitted and int(refit.config) == int(pycolmap.TwoViewGeometryConfiguration.PLANAR)
        np.testing.assert_array_equal(refit.inlier_matches, m)
        h.delete_two_view_geometry(1, 2)
        assert keep_or_fit(h, 1, 2, m, lambda: None) is None  # nothing stored, nothing fits


def test_write_scene_copy_keeps_the_scene_and_writes_the_given_matches(scene_db, tmp_path):
    db_path = _copy(scene_db.database, tmp_path / "s.db")
    fitted = []

    def fit(i, j, m):
        fitted.append((i, j, len(m)))
        return None  # the pair without a stored model is left out

    with ColmapDatabase(db_path) as db:
        m12 = db.matches(1, 2, "verified")[:10].astype(np.int64)
        m13 = db.matches(1, 3, "verified")[:5].astype(np.int64)
        db.handle.delete_two_view_geometry(1, 3)
        db.write_scene_copy(tmp_path / "copy.db", {(1, 2): m12, (1, 3): m13}, fit)
        raw = {im.image_id: db.raw_keypoints(im.image_id) for im in db.images()}
        stored = db.handle.read_two_view_geometry(1, 2)
    assert fitted == [(1, 3, 5)]
    with ColmapDatabase(tmp_path / "copy.db") as copy:
        assert [(im.image_id, im.name) for im in copy.images()] == [(i, str(i)) for i in sorted(raw)]
        for i, kp in raw.items():
            np.testing.assert_array_equal(copy.raw_keypoints(i), kp)  # every column
        assert [(p.image_id1, p.image_id2) for p in copy.pairs("verified")] == [(1, 2)]
        np.testing.assert_array_equal(copy.matches(1, 2, "verified"), m12)
        np.testing.assert_array_equal(copy.handle.read_two_view_geometry(1, 2).F, stored.F)


def test_a_scene_copy_of_the_matched_keypoints_only_indexes_the_same_points(scene_db, tmp_path):
    db_path = _copy(scene_db.database, tmp_path / "s.db")
    with ColmapDatabase(db_path) as db:
        m12 = db.matches(1, 2, "verified")[::3].astype(np.int64)
        m23 = db.matches(2, 3, "verified")[:7].astype(np.int64)
        written = db.write_scene_copy(tmp_path / "copy.db", {(1, 2): m12, (2, 3): m23}, lambda i, j, m: None,
                                      matched_keypoints_only=True)
        raw = {im.image_id: db.raw_keypoints(im.image_id) for im in db.images()}
    assert written is not None and sorted(written) == sorted(raw)
    np.testing.assert_array_equal(written[2], np.unique(np.concatenate([m12[:, 1], m23[:, 0]])))
    assert not any(len(written[i]) for i in raw if i not in (1, 2, 3))  # images in no pair keep none
    with ColmapDatabase(tmp_path / "copy.db") as copy:
        for i, kp in raw.items():
            np.testing.assert_array_equal(copy.raw_keypoints(i), kp[written[i]])
        for (i, j), m in {(1, 2): m12, (2, 3): m23}.items():
            c = copy.matches(i, j, "verified").astype(np.int64)
            np.testing.assert_array_equal(written[i][c[:, 0]], m[:, 0])  # the same keypoints, renumbered
            np.testing.assert_array_equal(written[j][c[:, 1]], m[:, 1])
            np.testing.assert_array_equal(copy.handle.read_two_view_geometry(i, j).inlier_matches, c)


def test_write_pair_updates_matches_and_geometry(scene_db, tmp_path):
    db_path = _copy(scene_db.database, tmp_path / "c.db")
    with ColmapDatabase(db_path) as db:
        m = db.matches(1, 2, "verified")
        keep = scene_db.is_true_match(1, 2, m)
        kept = m[keep]
        xy1, xy2 = db.keypoints(1)[kept[:, 0]], db.keypoints(2)[kept[:, 1]]
        config = db.write_pair(1, 2, kept, xy1, xy2, keep_model=True)
        assert config == "UNCALIBRATED"  # the synthetic scene's own model is kept
        config = db.write_pair(1, 3, db.matches(1, 3, "verified")[:0], xy1[:0], xy2[:0])
        assert config == "NONE"
        # no stored model: F fitted on the kept matches
        config = db.write_pair(2, 3, *_true(db, scene_db, 2, 3), keep_model=False)
        assert config == "UNCALIBRATED"
        F = db.handle.read_two_view_geometry(2, 3).F
    with ColmapDatabase(db_path) as db:
        np.testing.assert_array_equal(db.matches(1, 2, "verified"), kept)
        np.testing.assert_array_equal(db.matches(1, 2, "raw"), kept)
        assert (1, 3) not in {(p.image_id1, p.image_id2) for p in db.pairs("verified")}
        assert (1, 3) not in {(p.image_id1, p.image_id2) for p in db.pairs("raw")}
        kept23, a, b = _true(db, scene_db, 2, 3)
    # the fitted F explains the kept (noisy, 1 px) matches in COLMAP coordinates
    pa, pb = np.c_[a + 0.5, np.ones(len(a))], np.c_[b + 0.5, np.ones(len(b))]
    lines = pa @ F.T
    dist = np.abs(np.sum(lines * pb, axis=1)) / np.linalg.norm(lines[:, :2], axis=1)
    assert np.median(dist) < 2.0 * NOISE_PX


def _true(db, scene, i, j):
    m = db.matches(i, j, "raw")
    kept = m[scene.is_true_match(i, j, m)]
    return kept, db.keypoints(i)[kept[:, 0]], db.keypoints(j)[kept[:, 1]]


def test_validate_database_rejects_non_colmap_files(tmp_path, scene_db):
    text = tmp_path / "notes.db"
    text.write_text("hello\n")
    with pytest.raises(DatabaseError, match="not an SQLite file"):
        validate_database(text)
    other = tmp_path / "other.db"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE images (x)")
    con.commit()
    con.close()
    with pytest.raises(DatabaseError, match="missing tables: cameras, keypoints"):
        validate_database(other)
    missing = tmp_path / "nope.db"
    with pytest.raises(DatabaseError, match="not found"):
        validate_database(missing)
    with pytest.raises(DatabaseError, match="not found"):
        ColmapDatabase(missing)
    assert not missing.exists()  # pycolmap would have created an empty database
    validate_database(scene_db.database)


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def test_image_loader_gray_colour_16bit_missing(tmp_path):
    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    gray = rng.integers(0, 256, (25, 15), dtype=np.uint8)
    deep = (gray.astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "c.png"), colour)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    cv2.imwrite(str(tmp_path / "d.png"), deep)
    (tmp_path / "broken.jpg").write_bytes(b"not an image")
    names = {1: "c.png", 2: "g.png", 3: "d.png", 4: "broken.jpg", 5: "absent.png"}
    loader = ImageLoader(tmp_path, names, max_cached=2)
    c = loader[1]
    assert c.shape == (20, 30) and c.dtype == np.float32
    np.testing.assert_allclose(c, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY) / 255.0, atol=1e-6)
    np.testing.assert_allclose(loader[2], gray / 255.0, atol=1e-6)
    np.testing.assert_allclose(loader[3], gray / 255.0, atol=1e-6)
    # the CLI tests configure the "colmap_miho" logger (no propagation): listen directly
    collect = _Collect()
    logger = logging.getLogger("colmap_miho.adapters.images")
    logger.addHandler(collect)
    try:
        assert loader[4] is None and loader[5] is None and loader[5] is None
    finally:
        logger.removeHandler(collect)
    warned = collect.messages
    assert len(warned) == 2 and "broken.jpg" in warned[0] and "absent.png" in warned[1]
    assert len(loader._cache) <= 2  # bounded
    assert read_gray_float(tmp_path / "absent.png") is None


def test_keypoint_affines_are_the_shape_columns_and_hold_nothing_else(scene_db, tmp_path):
    db_path = _copy(scene_db.database, tmp_path / "a.db")
    rng = np.random.default_rng(0)
    with ColmapDatabase(db_path) as db:
        n = len(db.raw_keypoints(1))
        six = rng.normal(size=(n, 6)).astype(np.float32)
        db.handle.update_keypoints(1, six)
        aff = db.keypoint_affines(1)
        assert aff.shape == (n, 2, 2) and aff.dtype == np.float64
        np.testing.assert_array_equal(aff.reshape(n, 4), six[:, 2:6].astype(np.float64))
        # one image's frames, not a view into all its columns: at a million keypoints the rest is GBs
        assert (aff.base if aff.base is not None else aff).nbytes == n * 4 * 8
        four = np.column_stack([six[:, :2], np.full(n, 2.0, np.float32), np.full(n, np.pi / 2, np.float32)])
        db.handle.update_keypoints(1, four)
        np.testing.assert_allclose(db.keypoint_affines(1)[0], [[0.0, -2.0], [2.0, 0.0]], atol=1e-6)
