"""Blur matching (:mod:`colmap_miho.refinement.ncc.blur`) on scikit-image photographs.

Image 2 is a photograph under a known perspective warp with gain and offset, defocused by a
known Gaussian (and a little noise, as a camera adds after the optics); the estimate must
find which image is sharper and by about how much, leave equally sharp pairs alone, and
make the refinement more accurate on the defocused pair. No ../shared/data needed.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from colmap_miho.refinement.config import NCCConfig
from colmap_miho.refinement.ncc.blur import BLUR_LEVELS_PX, match_blur, smoothed
from colmap_miho.refinement.pairwise import refine_pair
from colmap_miho.refinement.warping import ImageStack

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")

#: the defocus of image 2 (pixels) and how far the chosen Gaussian may be from it: the
#: candidates are a grid (``BLUR_LEVELS_PX``), and NCC is flat near its best.
DEFOCUS_PX = 2.5
SIGMA_TOL_PX = 1.0
#: sensor noise added after the defocus (intensity, images in [0, 1]).
NOISE = 0.01
#: on the defocused pair, blur matching's median error is at most this fraction of NCC's
#: without it.
BLUR_GAIN = 0.8


def _pair(defocus: float, seed: int = 0):
    """(image 1, image 2, pts1, true pts2, start pts2, patch homography pairs)."""
    im = skdata.astronaut()
    img1 = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    h, w = img1.shape
    H = np.array([[0.98, 0.05, 7.3], [-0.04, 1.01, -5.2], [3e-5, -2e-5, 1.0]])
    img2 = cv2.warpPerspective(img1, H, (w, h), flags=cv2.INTER_LANCZOS4)
    if defocus > 0:
        img2 = cv2.GaussianBlur(img2, (0, 0), defocus)
    rng = np.random.default_rng(seed)
    img2 = (0.9 * img2 + 0.05 + rng.normal(0, NOISE, img2.shape)).astype(np.float32)
    pts1 = cv2.goodFeaturesToTrack((img1 * 255).astype(np.uint8), 300, 0.01, 10)
    pts1 = pts1.reshape(-1, 2).astype(np.float64)
    x = np.c_[pts1, np.ones(len(pts1))] @ H.T
    truth = x[:, :2] / x[:, 2:]
    m = 40
    keep = ((truth > m).all(axis=1) & (truth[:, 0] < w - m) & (truth[:, 1] < h - m)
            & (pts1 > m).all(axis=1) & (pts1[:, 0] < w - m) & (pts1[:, 1] < h - m))
    pts1, truth = pts1[keep], truth[keep]
    pts2 = truth + rng.uniform(-1.5, 1.5, truth.shape)
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(H)]), (len(pts1), 1, 1, 1))
    return img1, img2, pts1, truth, pts2, homs


def _tensors(*images):
    return tuple(torch.from_numpy(np.ascontiguousarray(im, dtype=np.float32)) for im in images)


def test_the_sharper_image_is_smoothed_by_about_the_defocus():
    """Image 1 is the sharper one; its frame is its own pixels (scale 1), so the smoothed
    copy is exactly :func:`smoothed` of it by one of the candidates."""
    img1, img2, pts1, _, pts2, homs = _pair(DEFOCUS_PX)
    t1, t2 = _tensors(img1, img2)
    (b1, b2), counts = match_blur((t1, t2), pts1, pts2, homs)
    assert counts == {"blur_pairs": 1, "blur_matched": len(pts1)}
    assert b2 is t2 and b1 is not t1
    used = [s for s in BLUR_LEVELS_PX if torch.allclose(b1, smoothed(t1, s), atol=1e-6)]
    assert len(used) == 1 and abs(used[0] - DEFOCUS_PX) <= SIGMA_TOL_PX, used


def test_equally_sharp_images_are_left_alone():
    img1, img2, pts1, _, pts2, homs = _pair(0.0)
    t1, t2 = _tensors(img1, img2)
    (b1, b2), counts = match_blur((t1, t2), pts1, pts2, homs)
    assert counts == {"blur_pairs": 0, "blur_matched": 0}
    assert b1 is t1 and b2 is t2


@pytest.mark.parametrize("lsm", [False, True])
def test_blur_matching_lowers_the_error_on_a_defocused_pair(lsm):
    img1, img2, pts1, truth, pts2, homs = _pair(DEFOCUS_PX)
    err = {}
    for on in (False, True):
        cfg = NCCConfig.pairwise(device="cpu", move="2", lsm=lsm, match_blur=on)
        res = refine_pair(img1, img2, pts1, pts2, homs, config=cfg)
        err[on] = np.median(np.linalg.norm(res.pts2 - truth, axis=1))
        assert res.stats.get("blur_matched", 0) == (len(pts1) if on else 0)
    start = np.median(np.linalg.norm(pts2 - truth, axis=1))
    assert err[True] < BLUR_GAIN * err[False], err
    assert err[True] < start, (err, start)


def test_each_image_pair_of_a_stack_is_estimated_on_its_own():
    """Two image pairs in one :class:`ImageStack` call, one defocused: only its matches read
    a smoothed copy, and every match's result equals that of its pair refined alone."""
    a1, a2, ap1, _, ap2, ahoms = _pair(DEFOCUS_PX, seed=1)
    b1, b2, bp1, _, bp2, bhoms = _pair(0.0, seed=2)
    na, nb = len(ap1), len(bp1)
    dev = torch.device("cpu")
    s1 = ImageStack.build(list(_tensors(a1, b1)), np.r_[np.zeros(na), np.ones(nb)].astype(int), dev)
    s2 = ImageStack.build(list(_tensors(a2, b2)), np.r_[np.zeros(na), np.ones(nb)].astype(int), dev)
    p1, p2, homs = np.r_[ap1, bp1], np.r_[ap2, bp2], np.r_[ahoms, bhoms]
    (o1, o2), counts = match_blur((s1, s2), p1, p2, homs)
    assert counts == {"blur_pairs": 1, "blur_matched": na}
    assert len(o1.images) == 3 and o2 is s2
    assert (o1.index[:na] == 2).all() and (o1.index[na:] == 1).all()
    cfg = NCCConfig.pairwise(device="cpu", move="2", match_blur=True)
    both = refine_pair(s1, s2, p1, p2, homs, config=cfg)
    alone_a = refine_pair(a1, a2, ap1, ap2, ahoms, config=cfg)
    alone_b = refine_pair(b1, b2, bp1, bp2, bhoms, config=cfg)
    assert np.array_equal(both.pts2[:na], alone_a.pts2)
    assert np.array_equal(both.pts2[na:], alone_b.pts2)

