"""Adapters shared by the product and the bench: pairs files, image decoding and sizes, building
a new COLMAP database (the +0.5 shift on the way in)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from colmap_miho.adapters.conventions import HALF_PIXEL
from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.adapters.hloc import read_pairs_file
from colmap_miho.adapters.images import image_size, read_gray_float, read_gray_uint8, read_image

pycolmap = pytest.importorskip("pycolmap")


# --------------------------------------------------------------------------- pairs files
def test_pairs_file_reads_hloc_pairs_and_pairs_with_gt(tmp_path):
    hloc_pairs = tmp_path / "pairs.txt"
    hloc_pairs.write_text("# retrieval\n\nsub/a.png sub/b.png\n  b.png   c.png  \n", encoding="utf-8")
    assert read_pairs_file(hloc_pairs) == [("sub/a.png", "sub/b.png"), ("b.png", "c.png")]
    # SuperGlue / LoFTR layout: name0 name1 rot0 rot1 K0(9) K1(9) T_0to1(16), read by report
    gt_row = " ".join(["0000.jpg", "0001.jpg", "0", "0"] + ["1.5"] * 34)
    with_gt = tmp_path / "pairs_with_gt.txt"
    with_gt.write_text(gt_row + "\n" + gt_row.replace("0001", "0002") + "\n", encoding="utf-8")
    assert read_pairs_file(with_gt) == [("0000.jpg", "0001.jpg"), ("0000.jpg", "0002.jpg")]


def test_pairs_file_errors_name_file_and_line(tmp_path):
    bad = tmp_path / "p.txt"
    bad.write_text("a.png b.png\nlonely.png\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"p\.txt:2: expected 'name0 name1 \.\.\.', got 'lonely\.png'"):
        read_pairs_file(bad)
    with pytest.raises(FileNotFoundError):
        read_pairs_file(tmp_path / "missing.txt")


def test_report_uses_the_adapters_pairs_reader():
    from colmap_miho.reporting import report

    assert report.read_pairs_file is read_pairs_file


# --------------------------------------------------------------------------- images
@pytest.fixture()
def image_files(tmp_path):
    rng = np.random.default_rng(1)
    colour = cv2.GaussianBlur(rng.integers(0, 256, (37, 53, 3), dtype=np.uint8), (5, 5), 0)
    paths = {"png": tmp_path / "c.png", "jpg": tmp_path / "c.jpg", "utf8": tmp_path / "çà.png"}
    cv2.imwrite(str(paths["png"]), colour)
    cv2.imwrite(str(paths["jpg"]), colour)
    paths["utf8"].write_bytes(paths["png"].read_bytes())
    return paths, colour


def test_read_gray_uint8_is_opencv_grayscale_decoding(image_files):
    paths, _ = image_files
    for key in ("png", "jpg"):
        expected = cv2.imread(str(paths[key]), cv2.IMREAD_GRAYSCALE)
        got = read_gray_uint8(paths[key])
        assert got.dtype == np.uint8 and got.shape == (37, 53)
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(read_gray_uint8(paths["utf8"]), read_gray_uint8(paths["png"]))


def test_read_image_sizes_and_missing_files(image_files, tmp_path):
    paths, colour = image_files
    np.testing.assert_array_equal(read_image(paths["png"]), colour)  # as stored, BGR
    assert image_size(paths["jpg"]) == (53, 37) and image_size(paths["utf8"]) == (53, 37)
    (tmp_path / "broken.png").write_bytes(b"no image")
    for bad in (tmp_path / "broken.png", tmp_path / "absent.png"):
        assert read_image(bad) is None and read_gray_float(bad) is None
        with pytest.raises(FileNotFoundError, match=f"cannot read image .*{bad.name}"):
            image_size(bad)
        with pytest.raises(FileNotFoundError, match=bad.name):
            read_gray_uint8(bad)


def test_folder_sizes_never_decode_a_file_no_image_decoder_knows(image_files, tmp_path, monkeypatch):
    """``run``'s size check read a video among the images whole into memory to decode it (2 GB
    and more: a cv2.error, "unexpected"): only a file whose first bytes name an image format is
    decoded."""
    import os
    import shutil

    from colmap_miho.adapters import images

    paths, _ = image_files
    folder = tmp_path / "folder"
    folder.mkdir()
    shutil.copy(paths["png"], folder / "a.png")
    (folder / "clip.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(1000))
    (folder / "notes.txt").write_text("not an image")
    decoded: list[str] = []
    read = images.read_image

    def reading(path, **kwargs):
        decoded.append(os.path.basename(path))
        return read(path, **kwargs)

    monkeypatch.setattr(images, "read_image", reading)
    assert images.folder_image_sizes(folder) == {"a.png": (53, 37)}
    assert decoded == []


def test_read_image_of_a_file_the_decoder_refuses_is_none(image_files, monkeypatch):
    import cv2

    def refuse(*args, **kwargs):
        raise cv2.error("(-215:Assertion failed) buf.checkVector(1, CV_8U) > 0 in function 'imdecode_'")

    monkeypatch.setattr(cv2, "imdecode", refuse)
    assert read_image(image_files[0]["png"]) is None


# --------------------------------------------------------------------------- new databases
def test_create_refuses_an_existing_path(tmp_path):
    existing = tmp_path / "x.db"
    existing.write_bytes(b"keep me")
    with pytest.raises(FileExistsError, match="x.db exists"):
        ColmapDatabase.create(existing)
    assert existing.read_bytes() == b"keep me"


def test_new_database_keypoints_shifted_once_and_matches(tmp_path):
    xy = np.array([[0.0, 0.0], [10.25, 3.5], [52.0, 36.0]])
    affines = np.array([[[2.0, 0.5], [-0.5, 2.0]]] * 3)
    path = tmp_path / "new.db"
    with ColmapDatabase.create(path) as db:
        with pytest.raises(ValueError, match="camera_model='NOPE' is not a COLMAP camera model"):
            db.add_camera("NOPE", 53, 37, 60.0)
        cam, rig = db.add_camera("SIMPLE_RADIAL", 53, 37, 60.0)
        a = db.add_image("a.png", cam, rig)
        b = db.add_image("b.png", cam, rig)
        db.add_keypoints(a, xy, affines)
        db.add_keypoints(b, xy + HALF_PIXEL, colmap_coordinates=True)
        db.add_matches(a, b, np.array([[0, 0], [2, 1]]), as_inliers=True)
        assert (db.num_images(), db.num_verified_pairs(), db.num_inlier_matches()) == (2, 1, 2)
    with pycolmap.Database.open(str(path)) as raw:  # independent read of what was stored
        ka, kb = np.asarray(raw.read_keypoints(a)), np.asarray(raw.read_keypoints(b))
        cams = raw.read_all_cameras()
        inliers = np.asarray(raw.read_two_view_geometry(a, b).inlier_matches)
    np.testing.assert_array_equal(ka[:, :2], (xy + 0.5).astype(np.float32))
    np.testing.assert_array_equal(ka[:, 2:], affines.reshape(-1, 4).astype(np.float32))
    np.testing.assert_array_equal(kb[:, :2], ka[:, :2])
    np.testing.assert_array_equal(kb[:, 2:], np.tile([1, 0, 0, 1], (3, 1)))
    assert len(cams) == 1 and (cams[0].width, cams[0].height) == (53, 37) and cams[0].params[0] == 60.0
    np.testing.assert_array_equal(inliers, [[0, 0], [2, 1]])
    with ColmapDatabase(path) as db:
        np.testing.assert_allclose(db.keypoints(a), xy, atol=1e-5)  # read back: shifted once
