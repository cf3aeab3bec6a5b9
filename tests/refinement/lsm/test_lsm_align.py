"""Least-squares matching (:mod:`colmap_miho.refinement.lsm.align`) on scikit-image photographs.

The search image is the photograph under a known affine map with gain and offset; the
rectification handed to LSM is off by a further small affine (what A must absorb), and the
start is off by up to 0.7 px (what t must absorb). No ../shared/data needed.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from colmap_miho.refinement.lsm import align
from colmap_miho.refinement.lsm.align import frame_sampler, lsm_align
from colmap_miho.refinement.warping import ImageStack, offset_grid

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")

#: median / 90th percentile shift error (px) on textured corners, bicubic sampling.
MEDIAN_TOL_PX = 0.02
P90_TOL_PX = 0.05
#: a match is accepted when it converged with a shift standard deviation below this (px).
SIGMA_GATE_PX = 0.05
#: true gain of the search image (1 / 0.8) and the tolerance on its estimate.
GAIN, GAIN_TOL = 1.25, 0.03
RADIUS = 8

# image 2 = 0.8 * image 1 (M^-1 x) + 0.1: x2 = M x1
_TH = np.deg2rad(10)
M_2FROM1 = np.array([[1.1 * np.cos(_TH), -0.95 * np.sin(_TH), 20.3],
                     [1.05 * np.sin(_TH), 0.97 * np.cos(_TH), -10.7], [0, 0, 1]])
Q = np.array([[1.04, 0.05], [-0.03, 0.98]])  # rectification error: true A = Q^-1


def _gray(name: str) -> np.ndarray:
    im = getattr(skdata, name)()
    if im.ndim == 3:
        im = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(im.astype(np.float32) / 255.0, (0, 0), 1.0)


def _problem(name: str, seed: int = 0, radius: int = RADIUS):
    """(search image, H_inv (J, 3, 3), centres (J, 2), templates (J, S, S), true shift (J, 2))."""
    img1 = _gray(name)
    h, w = img1.shape
    img2 = 0.8 * cv2.warpAffine(img1, M_2FROM1[:2], (w, h), flags=cv2.INTER_LANCZOS4) + 0.1
    pts = cv2.goodFeaturesToTrack((img1 * 255).astype(np.uint8), 300, 0.01, 8)
    pts = pts.reshape(-1, 2).astype(np.float64)
    m = 60
    pts = pts[(pts[:, 0] > m) & (pts[:, 0] < w - m) & (pts[:, 1] > m) & (pts[:, 1] < h - m)]
    J = len(pts)
    rng = np.random.default_rng(seed)
    noise = rng.uniform(-0.7, 0.7, (J, 2))
    # common frame y with image-2 pixel = M Q y; x1 = p sits at y = Q^-1 p
    Q3 = np.eye(3)
    Q3[:2, :2] = Q
    H_inv = torch.tensor(np.tile(M_2FROM1 @ Q3, (J, 1, 1)))
    centres = torch.tensor(pts @ np.linalg.inv(Q).T + noise)
    u = offset_grid(radius, torch.device("cpu")).numpy().astype(int)
    ix = pts.astype(int)
    tpl = img1[ix[:, 1:2] + u[:, 1], ix[:, 0:1] + u[:, 0]].reshape(J, 2 * radius + 1, -1)
    return torch.tensor(img2), H_inv, centres, torch.tensor(tpl), -noise


@pytest.mark.parametrize("name", ["camera", "astronaut"])
def test_lsm_recovers_affine_gain_offset(name):
    img2, H_inv, c, tpl, truth = _problem(name)
    res = lsm_align(frame_sampler(img2, H_inv, c), tpl, torch.zeros_like(c))
    acc = (res.converged & (res.sigma_max < SIGMA_GATE_PX)).numpy()
    assert acc.mean() > 0.95
    err = np.linalg.norm(res.shift.numpy() - truth, axis=1)[acc]
    assert np.median(err) < MEDIAN_TOL_PX, np.median(err)
    assert np.percentile(err, 90) < P90_TOL_PX
    A_err = np.abs(res.affine.numpy()[acc] - np.linalg.inv(Q)).max(axis=(1, 2))
    assert np.median(A_err) < 0.01
    assert abs(np.median(res.gain.numpy()[acc]) - GAIN) < GAIN_TOL
    # r0 + r1 * (0.8 g + 0.1) = g  =>  r0 = -0.1 r1
    assert abs(np.median(res.offset.numpy()[acc]) + 0.1 * GAIN) < GAIN_TOL
    assert (res.iterations.numpy()[acc] <= 10).all()


def test_shift_only_model_keeps_identity():
    img2, H_inv, c, tpl, _ = _problem("camera")
    res = lsm_align(frame_sampler(img2, H_inv, c), tpl[:20], torch.zeros_like(c[:20]),
                    affine=False)
    assert torch.equal(res.affine, torch.eye(2, dtype=torch.float64).repeat(20, 1, 1))


def _synthetic(kind: str, seed: int, size=64):
    """A flat patch or a straight blurred step edge, with a little noise of its own (the
    seed): two views of the same scene never share their noise."""
    rng = np.random.default_rng(seed)
    if kind == "flat":
        img = 0.5 + 0.002 * rng.standard_normal((size, size))
    else:
        x = np.arange(size)[None, :].repeat(size, 0)
        img = 0.2 + 0.6 * (x > size / 2 + 0.3) + 0.002 * rng.standard_normal((size, size))
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)


@pytest.mark.parametrize("kind", ["flat", "edge"])
def test_flat_and_edge_patches_fail_the_precision_test(kind):
    img = torch.tensor(_synthetic(kind, seed=4))
    ref = _synthetic(kind, seed=5)
    r = 6
    J = 4
    c = torch.tensor([[32.0, 32.0], [31.0, 30.0], [33.0, 34.0], [30.0, 33.0]])
    H_inv = torch.eye(3, dtype=torch.float64).repeat(J, 1, 1)
    u = offset_grid(r, torch.device("cpu")).numpy().astype(int)
    ix = c.numpy().astype(int)
    tpl = torch.tensor(ref[ix[:, 1:2] + u[:, 1], ix[:, 0:1] + u[:, 0]].reshape(J, 13, 13))
    start = torch.full((J, 2), 0.3, dtype=torch.float64)
    res = lsm_align(frame_sampler(img, H_inv, c), tpl, start)
    # the precision alone rejects them (along the edge, or everywhere when flat)
    assert (res.sigma_max > SIGMA_GATE_PX).all(), res.sigma_max


def _fields(res):
    return {k: getattr(res, k) for k in ("shift", "sigma", "sigma_max", "affine", "gain",
                                          "offset", "residual_std", "converged", "iterations")}


def _same(a: dict, b: dict, rows) -> None:
    for k in a:
        x, y = a[k][rows], b[k]
        assert torch.equal(torch.nan_to_num(x.double(), nan=7.0), torch.nan_to_num(y.double(), nan=7.0)), k


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("radius", [6, 8])
def test_result_is_bitwise_independent_of_the_batch(threads, radius):
    """Each match's result is the same alone, in any subset, in any order, and next to the
    matches of another image in an ImageStack."""
    img_a, H_a, c_a, tpl_a, _ = _problem("camera", seed=1, radius=radius)
    img_b, H_b, c_b, tpl_b, _ = _problem("astronaut", seed=2, radius=radius)
    n_a = 60
    H = torch.cat([H_a[:n_a], H_b[:40]])
    c = torch.cat([c_a[:n_a], c_b[:40]])
    tpl = torch.cat([tpl_a[:n_a], tpl_b[:40]])
    idx = torch.tensor([0] * n_a + [1] * 40)
    start = torch.zeros_like(c)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        stack = ImageStack.build([img_a, img_b], idx, torch.device("cpu"))
        full = _fields(lsm_align(frame_sampler(stack, H, c), tpl, start))
        rng = np.random.default_rng(0)
        perm = torch.as_tensor(rng.permutation(len(c)))
        cuts = [0, 1, 8, 41, 42, len(c)]
        for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
            rows = perm[lo:hi]
            part = lsm_align(frame_sampler(stack.rows(rows), H[rows], c[rows]), tpl[rows],
                             start[rows])
            _same(full, _fields(part), rows)
        # one image alone, no stack
        rows = torch.arange(n_a, n_a + 40)
        alone = lsm_align(frame_sampler(img_b, H[rows], c[rows]), tpl[rows], start[rows])
        _same(full, _fields(alone), rows)
    finally:
        torch.set_num_threads(old)
    assert full["converged"].float().mean() > 0.9


def _homography_pair():
    """(image 1, image 2, pts1, true pts2, start pts2, patch homography pairs): a perspective
    warp with gain/offset of a photograph, starts up to 1.5 px off."""
    img1 = _gray("astronaut")
    h, w = img1.shape
    H = np.array([[0.97, 0.06, 9.3], [-0.04, 1.02, -6.1], [4e-5, -3e-5, 1.0]])
    img2 = 0.9 * cv2.warpPerspective(img1, H, (w, h), flags=cv2.INTER_LANCZOS4) + 0.05
    pts1 = cv2.goodFeaturesToTrack((img1 * 255).astype(np.uint8), 300, 0.01, 10)
    pts1 = pts1.reshape(-1, 2).astype(np.float64)
    x = np.c_[pts1, np.ones(len(pts1))] @ H.T
    truth = x[:, :2] / x[:, 2:]
    keep = (truth > 40).all(axis=1) & (truth[:, 0] < w - 40) & (truth[:, 1] < h - 40)
    keep &= (pts1 > 40).all(axis=1) & (pts1[:, 0] < w - 40) & (pts1[:, 1] < h - 40)
    pts1, truth = pts1[keep], truth[keep]
    rng = np.random.default_rng(0)
    pts2 = truth + rng.uniform(-1.5, 1.5, truth.shape)
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(H)]), (len(pts1), 1, 1, 1))
    return img1, img2, pts1, truth, pts2, homs


def test_refine_pair_with_lsm_lowers_the_error_on_a_known_homography():
    """The pairwise refiner with ``lsm.enabled``: on a perspective warp with gain/offset of a
    photograph, LSM's positions are closer to the truth than NCC's, and every LSM outcome
    is counted."""
    from colmap_miho.refinement.config import NCCConfig
    from colmap_miho.refinement.pairwise import refine_pair

    img1, img2, pts1, truth, pts2, homs = _homography_pair()
    err = {}
    for lsm in (False, True):
        cfg = NCCConfig.pairwise(device="cpu", move="2", template_radius=6, lsm={"enabled": lsm})
        res = refine_pair(img1, img2, pts1, pts2, homs, config=cfg)
        moved = res.moved_side == 2
        err[lsm] = np.median(np.linalg.norm(res.pts2[moved] - truth[moved], axis=1))
        if lsm:
            counted = sum(res.stats[k] for k in ("lsm_applied", "lsm_not_converged", "lsm_far",
                                                  "lsm_imprecise"))
            assert counted == res.stats["moved"]
            assert res.stats["lsm_applied"] > 0.5 * res.stats["moved"]
    assert err[True] < 0.7 * err[False], err


def _scaled_pair(scale: float):
    """(image 1, image 2, pts1, true pts2, start pts2, homography pairs): image 2 is image 1
    seen ``scale`` times as large (< 1: farther), rendered as a camera would (smoothed to
    its own pixel size first, 0.5 px of its own), with gain/offset; starts up to 1.5 px off."""
    img1 = _gray("camera")
    h, w = img1.shape
    H = np.array([[scale * 0.99, 0.04 * scale, 9.3], [-0.03 * scale, scale * 1.01, -6.1],
                  [2e-5, -1e-5, 1.0]])
    pre = cv2.GaussianBlur(img1, (0, 0), 0.5 * np.sqrt(1 / scale**2 - 1))
    img2 = 0.9 * cv2.warpPerspective(pre, H, (w, h), flags=cv2.INTER_LANCZOS4) + 0.05
    pts1 = cv2.goodFeaturesToTrack((img1 * 255).astype(np.uint8), 400, 0.01, 10)
    pts1 = pts1.reshape(-1, 2).astype(np.float64)
    x = np.c_[pts1, np.ones(len(pts1))] @ H.T
    truth = x[:, :2] / x[:, 2:]
    keep = ((truth > 40).all(axis=1) & (truth[:, 0] < w - 40) & (truth[:, 1] < h - 40)
            & (pts1 > 40).all(axis=1) & (pts1[:, 0] < w - 40) & (pts1[:, 1] < h - 40))
    pts1, truth = pts1[keep], truth[keep]
    pts2 = truth + np.random.default_rng(0).uniform(-1.5, 1.5, truth.shape)
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(H)]), (len(pts1), 1, 1, 1))
    return img1, img2, pts1, truth, pts2, homs


#: with image 2 at half / 0.7 the scale of image 1, anti-aliased LSM's median error is at
#: most this fraction of plain LSM's.
ANTIALIAS_GAIN = 0.6


@pytest.mark.parametrize("scale", [0.5, 0.7])
def test_antialiasing_the_finer_view_lowers_the_error(scale):
    """The finer view (image 1) smoothed to the coarser one's blur before LSM reads it: the
    two patches then differ by the geometric and radiometric model alone."""
    from colmap_miho.refinement.config import NCCConfig
    from colmap_miho.refinement.pairwise import refine_pair

    img1, img2, pts1, truth, pts2, homs = _scaled_pair(scale)
    err = {}
    for aa in (0.0, 0.5):
        cfg = NCCConfig.pairwise(device="cpu", move="2", template_radius=6,
                                 lsm={"enabled": True, "radius": 8, "antialias": aa})
        res = refine_pair(img1, img2, pts1, pts2, homs, config=cfg)
        err[aa] = np.median(np.linalg.norm(res.pts2 - truth, axis=1))
    assert err[0.5] < ANTIALIAS_GAIN * err[0.0], err


def test_antialiased_lsm_is_per_match():
    """A match's anti-aliased LSM result is bitwise the same in any subset of the call."""
    from colmap_miho.refinement.config import NCCConfig
    from colmap_miho.refinement.pairwise import refine_pair

    img1, img2, pts1, _, pts2, homs = _scaled_pair(0.6)
    cfg = NCCConfig.pairwise(device="cpu", move="2", template_radius=6,
                             lsm={"enabled": True, "radius": 8, "antialias": 0.5})
    full = refine_pair(img1, img2, pts1, pts2, homs, config=cfg)
    rows = np.random.default_rng(3).permutation(len(pts1))[: len(pts1) // 3]
    part = refine_pair(img1, img2, pts1[rows], pts2[rows], homs[rows], config=cfg)
    assert np.array_equal(full.pts2[rows], part.pts2)


def test_frame_jacobian_matches_finite_differences():
    from colmap_miho.refinement.warping import frame_jacobian

    H = torch.tensor([[[1.1, 0.2, 5.0], [-0.1, 0.9, 3.0], [1e-3, -2e-3, 1.0]]], dtype=torch.float64)
    p = torch.tensor([[40.0, 25.0]], dtype=torch.float64)

    def f(q):
        v = H[0] @ torch.cat([q, torch.ones(1, dtype=torch.float64)])
        return v[:2] / v[2]

    eps = 1e-6
    num = torch.stack([(f(p[0] + eps * e) - f(p[0] - eps * e)) / (2 * eps)
                       for e in torch.eye(2, dtype=torch.float64)], dim=1)
    assert torch.allclose(frame_jacobian(H, p)[0], num, atol=1e-7)


#: positions read by frame_sampler (float32 grid) against a float64 mapping of every sample (px).
SAMPLE_POS_TOL_PX = 1e-4


@pytest.mark.parametrize("stack", [False, True])
def test_frame_sampler_reads_the_mapped_positions(stack, monkeypatch):
    """``frame_sampler`` reads match j's image at ``H_inv[j] (c[j] + t + A u)`` (the map
    composed once per match, grouped by image in a stack): on a smooth ramp image the value
    is the x coordinate of the sample, so the values give the positions read (read here with
    bilinear sampling: it reproduces a ramp exactly; grid_sample's bicubic, a = -0.75, does not)."""
    monkeypatch.setattr(align, "_grid_sample", lambda image, grid: F.grid_sample(
        image[None, None], grid[None], mode="bilinear", padding_mode="border", align_corners=True)[0, 0])
    h, w = 200, 300
    ramp = torch.arange(w, dtype=torch.float32)[None].expand(h, w).contiguous()
    rng = np.random.default_rng(3)
    J, r = 12, 3
    H = np.tile(np.eye(3), (J, 1, 1))
    H[:, :2, :2] += rng.uniform(-0.1, 0.1, (J, 2, 2))
    H[:, :2, 2] = rng.uniform(-5, 5, (J, 2))
    H[:, 2, :2] = rng.uniform(-2e-4, 2e-4, (J, 2))
    c = torch.tensor(rng.uniform(80, 120, (J, 2)))
    A = torch.tensor(np.eye(2) + rng.uniform(-0.2, 0.2, (J, 2, 2)))
    t = torch.tensor(rng.uniform(-1, 1, (J, 2)))
    image = ImageStack.build([ramp, ramp + 0.0], torch.tensor(rng.integers(0, 2, J)),
                             torch.device("cpu")) if stack else ramp
    rows = torch.tensor([5, 0, 7, 3, 11])
    vals = frame_sampler(image, torch.tensor(H), c)(rows, A[rows], t[rows], r)
    u = offset_grid(r, torch.device("cpu")).numpy()
    for k, j in enumerate(rows.tolist()):
        p = c[j].numpy() + t[j].numpy() + u @ A[j].numpy().T
        q = np.c_[p, np.ones(len(p))] @ H[j].T
        x = q[:, 0] / q[:, 2]
        got = vals[k].reshape(-1).numpy()
        err = np.abs(got - x).max()
        assert err < SAMPLE_POS_TOL_PX, err
