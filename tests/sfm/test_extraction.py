"""COLMAP's extraction through ``run``: a camera mode that would give images of different sizes
one camera is refused before anything is extracted, naming the images; an image COLMAP could
not use is named, not dropped in silence."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from colmap_miho.adapters.images import folder_image_sizes
from colmap_miho.cli import main
from colmap_miho.errors import InvalidInput
from colmap_miho.sfm.extraction import extract_and_match


def _texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A blurred random texture SIFT finds features in."""
    return cv2.GaussianBlur((rng.uniform(0, 255, (h, w))).astype(np.uint8), (0, 0), 1.5)


@pytest.fixture
def mixed(tmp_path):
    """Three 160x120 images in the folder itself and two 200x150 ones in ``wide/``."""
    rng = np.random.default_rng(0)
    root = tmp_path / "images"
    (root / "wide").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(root / f"a{k}.png"), _texture(rng, 160, 120))
    for k in range(2):
        cv2.imwrite(str(root / "wide" / f"b{k}.png"), _texture(rng, 200, 150))
    (root / "notes.txt").write_text("not an image")
    return root


def test_folder_image_sizes_reads_the_headers(mixed):
    assert folder_image_sizes(mixed) == {"a0.png": (160, 120), "a1.png": (160, 120), "a2.png": (160, 120),
                                         "wide/b0.png": (200, 150), "wide/b1.png": (200, 150)}


def test_one_camera_for_images_of_two_sizes_is_refused_before_extracting(mixed, tmp_path, capfd):
    out = tmp_path / "work"
    assert main(["run", "--images", str(mixed), "--output", str(out), "-q"]) == 2
    line = capfd.readouterr().err
    assert "2 sizes" in line and "160x120: 3 image(s)" in line and "200x150: 2 image(s), e.g. wide/b0.png" in line
    assert "--camera-mode per_folder" in line
    assert not (out / "database.db").exists()


def test_a_camera_mode_that_fits_the_sizes_extracts_every_image(mixed, tmp_path):
    with pytest.raises(InvalidInput, match="sizes"):
        extract_and_match(mixed, tmp_path / "single.db", camera_mode="single", max_features=256, num_threads=1)
    info = extract_and_match(mixed, tmp_path / "folder.db", camera_mode="per_folder", max_features=256,
                             num_threads=1)
    assert info["num_images"] == info["images_found"] == 5 and info["images_not_extracted"] == []


def test_an_image_colmap_cannot_use_is_named(mixed, tmp_path, caplog):
    """A WebP image: Pillow reads it, COLMAP's reader does not and skips it with a line in its
    own log only; the run names it."""
    from PIL import Image

    for p in (mixed / "wide").iterdir():
        p.unlink()
    (mixed / "wide").rmdir()
    Image.open(mixed / "a2.png").save(mixed / "a3.webp")
    info = extract_and_match(mixed, tmp_path / "db.db", max_features=256, num_threads=1)
    assert info["num_images"] == 3 and info["images_found"] == 4 and info["images_not_extracted"] == ["a3.webp"]
    assert any("1 of the 4 images" in r.getMessage() and "a3.webp" in r.getMessage() for r in caplog.records)
