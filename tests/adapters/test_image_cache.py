"""ImageLoader's cache: bounded by images and by bytes (LRU), and its count of decodes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from colmap_miho.adapters.images import ImageLoader, read_gray_float


@pytest.fixture
def folder(tmp_path):
    """Five gray PNGs of 10x10 px (400 bytes each as float32) and one 20x10 (800 bytes)."""
    rng = np.random.default_rng(1)
    names = {}
    for i in range(1, 6):
        cv2.imwrite(str(tmp_path / f"{i}.png"), rng.integers(0, 256, (10, 10), dtype=np.uint8))
        names[i] = f"{i}.png"
    cv2.imwrite(str(tmp_path / "big.png"), rng.integers(0, 256, (10, 20), dtype=np.uint8))
    names[6] = "big.png"
    return tmp_path, names


def test_byte_budget_is_lru_by_bytes(folder):
    root, names = folder
    loader = ImageLoader(root, names, max_cached=None, max_cached_bytes=1000)
    for i in (1, 2):
        loader[i]
    assert loader.decodes == 2 and loader.cached_bytes == 800
    loader[1]  # hit: 1 becomes the most recent
    assert loader.decodes == 2
    loader[6]  # 800 bytes: 2 (least recent) and then 1 must go to fit 1000 bytes
    assert loader.cached_bytes == 800 and list(loader._cache) == [6]
    loader[3]
    loader[4]  # 6 (800) + 3 (400) + 4 (400) > 1000: 6 goes
    assert list(loader._cache) == [3, 4] and loader.cached_bytes == 800
    assert loader.decodes == 5
    loader[3]
    assert loader.decodes == 5
    np.testing.assert_array_equal(loader[3], read_gray_float(root / "3.png"))


def test_image_over_the_budget_is_returned_not_kept(folder):
    root, names = folder
    loader = ImageLoader(root, names, max_cached=None, max_cached_bytes=500)
    loader[1]
    assert loader[6].shape == (10, 20)
    assert list(loader._cache) == [1]
    loader[6]
    assert loader.decodes == 3


def test_count_bound_still_works_and_both_apply(folder):
    root, names = folder
    by_count = ImageLoader(root, names, max_cached=2)
    for i in (1, 2, 3, 1):
        by_count[i]
    assert list(by_count._cache) == [3, 1] and by_count.decodes == 4
    both = ImageLoader(root, names, max_cached=2, max_cached_bytes=10_000)
    for i in (1, 2, 3):
        both[i]
    assert len(both._cache) == 2
    with pytest.raises(ValueError, match="max_cached"):
        ImageLoader(root, names, max_cached=0)
    with pytest.raises(ValueError, match="max_cached_bytes"):
        ImageLoader(root, names, max_cached_bytes=-1)


def test_check_all_counts_its_decodes_and_keeps_what_fits(folder):
    root, names = folder
    (root / "bad.png").write_bytes(b"not an image")
    names = {**names, 7: "bad.png", 8: "absent.png"}
    sizes = {i: (10, 10) for i in range(1, 6)}
    sizes[6] = (20, 10)
    loader = ImageLoader(root, names, max_cached=None, max_cached_bytes=1200, expected_sizes=sizes)
    assert loader.check_all() == [7, 8]
    # 1, 2, 3 fit (1200 bytes); nothing is evicted for the later ones
    assert list(loader._cache) == [1, 2, 3] and loader.cached_bytes == 1200
    assert loader.decodes == 7  # 6 images and the broken file (the absent one is not decoded)
    for i in (1, 2, 3):
        np.testing.assert_array_equal(loader[i], read_gray_float(root / names[i]))
    assert loader.decodes == 7 and loader.loads == 0  # served from the cache
    loader[4]  # evicts 1, the least recently used
    assert loader.decodes == 8 and list(loader._cache) == [2, 3, 4]
    # again: the known bad ones and the cached ones are not decoded, 1, 5 and 6 are
    assert loader.check_all() == [7, 8] and loader.decodes == 8 + 3


def test_check_all_with_a_count_bound_keeps_the_first(folder):
    root, names = folder
    loader = ImageLoader(root, names, max_cached=2)
    assert loader.check_all() == []
    assert list(loader._cache) == [1, 2] and loader.decodes == 6


def test_add_images_keeps_the_cache(folder):
    root, names = folder
    loader = ImageLoader(root, {1: names[1]}, max_cached=None, max_cached_bytes=4000)
    loader[1]
    loader.add_images({2: names[2]}, {2: (10, 10)})
    loader[2]
    loader[1]
    assert loader.decodes == 2 and loader.image_bytes(2) == 400 and loader.image_bytes(1) is None
    loader.add_images({1: names[3]})  # renamed: the old pixels are dropped
    np.testing.assert_array_equal(loader[1], read_gray_float(root / names[3]))
    assert loader.decodes == 3
    again = ImageLoader(**loader.state())
    assert again.names == loader.names and again.max_cached_bytes == 4000 and again.decodes == 0


def test_clear_cache_frees_the_budget(folder):
    root, names = folder
    loader = ImageLoader(root, names, max_cached=None, max_cached_bytes=10**6)
    for i in (1, 2, 3):
        loader[i]
    assert loader.cached_bytes == 1200 and loader.decodes == 3
    loader.clear_cache()
    assert loader.cached_bytes == 0 and not loader._cache
    loader[1]
    assert loader.decodes == 4 and loader.cached_bytes == 400  # decoded again, kept again
