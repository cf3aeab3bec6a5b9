"""``NCCConfig.inner_radius``: the offsets near the keypoint are searched first, the full search
radius only where the near peak lies on that smaller window's border.

Synthetic scenes (no ../shared/data): a smooth random texture warped by a known homography.
"""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.refinement.config import NCCConfig
from colmap_miho.refinement.pairwise import refine_pair
from miho_bench.variants import variant

cv2 = pytest.importorskip("cv2")

#: refined positions of the near-first and the full search agree within this (common-frame
#: pixels); they differ only by the float32 rounding of NCC over windows of other sizes
#: (measured: below 1e-4 px on this scene).
SAME_POSITION_PX = 1e-3
#: median error of the refined keypoints on this noise-free scene (measured 0.04 px).
MEDIAN_ERROR_PX = 0.06
H_SCENE = np.array([[0.98, 0.05, 6.3], [-0.03, 1.01, -4.2], [3e-5, -2e-5, 1.0]])


def _texture(rng: np.random.Generator, h: int = 240, w: int = 320) -> np.ndarray:
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.6)
    return (img - img.min()) / (img.max() - img.min())


def test_config_validation():
    with pytest.raises(ValueError, match="inner_radius"):
        NCCConfig.pairwise(inner_radius=-1)
    # a radius at or above the search radius leaves the full search (a recipe's inner radius
    # must not forbid a smaller search radius)
    assert NCCConfig.pairwise(search_radius=2, inner_radius=2).inner_radius == 2


@pytest.mark.parametrize("offset_px", [1.0, 2.5, 4.0])
def test_far_peaks_are_still_followed(offset_px):
    """Starts up to 4 px from the truth (twice the near radius): the near window's peak sits
    on its border wherever the truth lies beyond it, and the full search takes over, so the
    result is the full search's."""
    rng = np.random.default_rng(0)
    img1 = _texture(rng)
    h, w = img1.shape
    img2 = cv2.warpPerspective(img1, H_SCENE, (w, h), flags=cv2.INTER_LINEAR)
    n = 200
    pts1 = rng.uniform([30.0, 30.0], [w - 30.0, h - 30.0], (n, 2))
    x = np.c_[pts1, np.ones(n)] @ H_SCENE.T
    gt2 = x[:, :2] / x[:, 2:]
    angle = rng.uniform(0.0, 2 * np.pi, n)
    pts2 = gt2 + offset_px * np.c_[np.cos(angle), np.sin(angle)]
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(H_SCENE)]), (n, 1, 1, 1))
    res = {s0: refine_pair(img1, img2, pts1, pts2, homs, move="2",
                           config=NCCConfig.pairwise(device="cpu", template_radius=6, inner_radius=s0))
           for s0 in (0, 2, 10)}
    for name in ("pts2", "ncc_after", "moved_side", "rejected"):  # 10 = s: the full search
        np.testing.assert_array_equal(getattr(res[10], name), getattr(res[0], name))
    assert res[2].stats["moved"] == res[0].stats["moved"] >= 0.95 * n
    np.testing.assert_array_equal(res[2].moved_side, res[0].moved_side)
    np.testing.assert_allclose(res[2].pts2, res[0].pts2, atol=SAME_POSITION_PX)
    assert np.median(np.linalg.norm(res[2].pts2 - gt2, axis=1)) < MEDIAN_ERROR_PX


def test_a_near_local_maximum_is_kept():
    """The exact copy of each template lies 8 px away, a noisy copy at the keypoint: the full
    search jumps to the exact copy (the higher peak), the near-first search keeps the noisy
    copy's peak, a local maximum inside its window."""
    rng = np.random.default_rng(3)
    img1 = _texture(rng, 200, 200)
    img2 = np.clip(img1 + rng.normal(0.0, 0.04, img1.shape).astype(np.float32), 0.0, 1.0)
    r, jump = 3, 8
    pts = np.array([[x, y] for y in (40, 80, 120, 160) for x in (40, 90, 140)], dtype=np.float64)
    for x, y in pts.astype(int):  # the exact 7x7 template, pasted 8 px to the right
        img2[y - r:y + r + 1, x + jump - r:x + jump + r + 1] = img1[y - r:y + r + 1, x - r:x + r + 1]
    homs = np.tile(np.eye(3), (len(pts), 2, 1, 1))
    cfg = {"device": "cpu", "template_radius": r, "search_radius": 10}
    full = refine_pair(img1, img2, pts, pts, homs, move="2",
                       config=variant(NCCConfig.pairwise(**cfg), subpixel_iterations=0))
    near = refine_pair(img1, img2, pts, pts, homs, move="2",
                       config=variant(NCCConfig.pairwise(**cfg, inner_radius=2), subpixel_iterations=0))
    np.testing.assert_allclose(full.pts2, pts + [jump, 0.0], atol=0.5)  # its integer peak
    assert np.all(np.abs(near.pts2 - pts) <= 1.0)
    assert np.all(near.ncc_after < full.ncc_after)
