"""Images renamed or shuffled after extraction: keypoints that do not stand out from their
surroundings in the image file are said, before they are refined on the wrong pixels."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from colmap_miho.pipeline.plausibility import MIN_KEYPOINTS, implausible, keypoint_support


def _blobs(rng: np.random.Generator, xy: np.ndarray, size: int = 400, sigma: float = 2.0) -> np.ndarray:
    """A noisy image with a Gaussian blob at each of ``xy``: blobs are what a DoG detector finds."""
    yy, xx = np.mgrid[0:size, 0:size]
    img = rng.normal(0.5, 0.02, (size, size))
    for x, y in xy:
        img += 0.4 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2))
    return img.astype(np.float32)


def test_keypoints_stand_out_only_in_their_own_image():
    rng = np.random.default_rng(0)
    xy = rng.uniform(10, 390, (600, 2))
    own = _blobs(rng, xy)
    other = _blobs(rng, rng.uniform(10, 390, (600, 2)))
    scale = np.full(len(xy), 2.0)
    share, n = keypoint_support(own, xy, scale)
    assert n == MIN_KEYPOINTS and share > 0.8 and not implausible(share, n)
    share, n = keypoint_support(other, xy, scale)
    assert abs(share - 0.5) < 0.1 and implausible(share, n)
    assert not implausible(0.3, MIN_KEYPOINTS - 1)  # too few keypoints: no verdict


@pytest.mark.slow
def test_two_swapped_images_are_named(shared_data, tmp_path):
    """The temple's database with two of its image files swapped: both are named in the summary
    and the warnings, no other image is."""
    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.sfm.extraction import extract_and_match

    root = shared_data / "middlebury_temple_sparse_ring"
    db = tmp_path / "db.db"
    extract_and_match(root / "images", db, max_features=2048, num_threads=2)
    images = tmp_path / "images"
    shutil.copytree(root / "images", images)
    with ColmapDatabase(db) as d:
        names = sorted(im.name for im in d.images())
    a, b = names[0], names[8]
    (images / a).rename(tmp_path / "a")
    (images / b).rename(images / a)
    (tmp_path / "a").rename(images / b)
    summary = refine_database(db, images, tmp_path / "out.db", workers=1,
                              recipe="mop_miho_ncc")
    assert sorted(summary.images_implausible) == sorted([a, b])
