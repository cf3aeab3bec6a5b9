"""The compiled LSM kernel (:mod:`colmap_miho.refinement.lsm.kernel`) against the torch path
(:func:`~colmap_miho.refinement.lsm.align.frame_sampler` + :func:`~colmap_miho.refinement.lsm.align.lsm_align`),
on a perspective warp with gain and offset of scikit-image photographs. No ../shared/data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from colmap_miho.refinement.lsm import kernel as lsm_kernel
from colmap_miho.refinement.lsm.align import frame_sampler, lsm_align
from colmap_miho.refinement.warping import ImageStack

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")
#: samples of the kernel against grid_sample's (intensity units of [0, 1] images): the
#: torch path rounds each position to float32 grid units (about 1e-4 px on these images).
SAMPLE_TOL = 2e-4
#: the final shifts of kernel and torch path (px), on the matches both stop at the same step.
SHIFT_TOL_PX = 2e-4
#: their a-posteriori standard deviations, relative.
SIGMA_REL_TOL = 1e-3
#: share of matches with the same iteration count and the same convergence flag at least:
#: a shift update within rounding of the tolerance can stop one path a step earlier.
SAME_STOP_SHARE = 0.97
RADIUS = 8
SIGMA_PX = 0.7


def _gray(name: str) -> np.ndarray:
    im = getattr(skdata, name)()
    if im.ndim == 3:
        im = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(im.astype(np.float32) / 255.0, (0, 0), 1.0)


def _problem(name: str, seed: int):
    """Image 1, image 2 (perspective warp with gain/offset of image 1), H_f_inv (identity:
    the frame is image 1), H_m_inv (frame -> image 2), frame points (J, 2) and starts (J, 2)
    up to 1 px off (the true shift is 0)."""
    img1 = _gray(name)
    h, w = img1.shape
    H = np.array([[0.97, 0.06, 9.3], [-0.04, 1.02, -6.1], [4e-5, -3e-5, 1.0]])
    img2 = 0.9 * cv2.warpPerspective(img1, H, (w, h), flags=cv2.INTER_LANCZOS4) + 0.05
    pts = cv2.goodFeaturesToTrack((img1 * 255).astype(np.uint8), 200, 0.01, 10).reshape(-1, 2)
    pts = pts[(pts > 30).all(axis=1) & (pts[:, 0] < w - 30) & (pts[:, 1] < h - 30)].astype(np.float64)
    J = len(pts)
    rng = np.random.default_rng(seed)
    start = rng.uniform(-1.0, 1.0, (J, 2))
    t = torch.tensor
    return (t(img1), t(img2.astype(np.float32)), t(np.tile(np.eye(3), (J, 1, 1))), t(np.tile(H, (J, 1, 1))),
            t(pts), t(start))


def _blur(J: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every other match smoothed (sigma up to SIGMA_PX), the rest not."""
    rng = np.random.default_rng(seed)
    on = torch.as_tensor(np.arange(J) % 2 == 0)
    return on, torch.as_tensor(rng.uniform(0.2, SIGMA_PX, J))


def _torch_path(img_f, img_m, Hf, Hm, c, start, blur_f, blur_m, **kw):
    J = c.shape[0]
    eye = torch.eye(2, dtype=torch.float64).expand(J, 2, 2)
    tpl = frame_sampler(img_f, Hf, c, blur_px=blur_f)(
        torch.arange(J), eye, torch.zeros((J, 2), dtype=torch.float64), RADIUS)
    return lsm_align(frame_sampler(img_m, Hm, c, blur_px=blur_m), tpl, start, **kw)


@pytest.mark.parametrize("sigma", [0.0, 0.35, 1.3])
def test_kernel_reads_what_grid_sample_reads(sigma):
    """The kernel's bicubic read (plain and smoothed) gives grid_sample's values, including
    positions past the image border (taps clamped)."""
    img1, img2, _, Hm, c, start = _problem("camera", 0)
    lsm_kernel.KERNELS()  # the jitted helpers
    h, w = img2.shape
    # some matches pushed across the border
    c = c.clone()
    c[:5, 0] = torch.tensor([-3.0, 0.4, 1.5, w - 1.2, w + 2.7])
    c[5:10, 1] = torch.tensor([-2.2, 0.1, 0.9, h - 0.6, h + 4.0])
    J = c.shape[0]
    A = torch.tensor([[1.02, 0.03], [-0.05, 0.97]], dtype=torch.float64).expand(J, 2, 2)
    on = torch.ones(J, dtype=torch.bool) if sigma > 0 else torch.zeros(J, dtype=torch.bool)
    sg = torch.full((J,), sigma, dtype=torch.float64)
    ref = frame_sampler(img2, Hm, c, blur_px=(on, sg))(torch.arange(J), A, start, RADIUS).numpy()
    side = 2 * RADIUS + 1
    out = np.empty((side, side))
    wts, taps = np.empty((2, 4, side)), np.empty((2, side), np.int64)
    cw, base = np.empty((2, side, int(2 * sigma) + 6)), np.empty((4, side), np.int64)
    Hn, cn, sn, An = Hm.numpy(), c.numpy(), start.numpy(), A.numpy()
    for j in range(J):
        a = An[j]
        lsm_kernel._read_blurred(img2.numpy(), Hn[j], cn[j, 0] + sn[j, 0], cn[j, 1] + sn[j, 1], a[0, 0], a[0, 1],
                                 a[1, 0], a[1, 1], RADIUS, lsm_kernel.KEYS_A, bool(on[j]), sigma, out, wts,
                                 taps, cw, base)
        assert np.abs(out - ref[j]).max() < SAMPLE_TOL, (j, np.abs(out - ref[j]).max())


@pytest.mark.parametrize(("blur", "affine"), [(False, True), (True, True), (True, False)])
def test_kernel_matches_the_torch_path(blur, affine):
    """Same model, stop rule and precision as the torch path: the shifts agree to float
    rounding where both stop at the same step, and nearly every match does."""
    img1, img2, Hf, Hm, c, start = _problem("astronaut", 1)
    J = c.shape[0]
    bf = _blur(J, 2) if blur else None
    bm = _blur(J, 3) if blur else None
    kw = dict(affine=affine, max_iterations=10, tol_px=0.01, max_shift_px=2.0)
    ref = _torch_path(img1, img2, Hf, Hm, c, start, bf, bm, **kw)
    got = lsm_kernel.lsm_frames(img1, img2, Hf, c, Hm, c, start, RADIUS, blur_f=bf, blur_m=bm, **kw)
    same = (ref.iterations == got.iterations) & (ref.converged == got.converged)
    assert same.float().mean() >= SAME_STOP_SHARE
    assert ref.converged.float().mean() > 0.8
    d = (ref.shift - got.shift)[same].abs().max()
    assert d < SHIFT_TOL_PX, d
    ok = same & ref.converged
    rel = ((ref.sigma_max - got.sigma_max) / ref.sigma_max)[ok].abs().max()
    assert rel < SIGMA_REL_TOL, rel
    assert torch.allclose(ref.affine[ok], got.affine[ok], atol=1e-4)
    assert torch.allclose(ref.gain[ok], got.gain[ok], rtol=1e-4)


def _fields(r) -> dict[str, np.ndarray]:
    return {k: getattr(r, k).numpy() for k in ("shift", "sigma", "sigma_max", "affine", "gain", "offset",
                                               "residual_std", "converged", "iterations")}


def test_kernel_result_is_bitwise_independent_of_the_batch():
    """A match's result is bitwise the same alone, in any subset and order, and next to the
    matches of another image pair (ImageStack)."""
    a = _problem("camera", 4)
    b = _problem("astronaut", 5)
    n_a, n_b = 50, 40
    Hf, Hm, c, start = (torch.cat([a[k][:n_a], b[k][:n_b]]) for k in (2, 3, 4, 5))
    J = n_a + n_b
    idx = torch.tensor([0] * n_a + [1] * n_b)
    st_f = ImageStack.build([a[0], b[0]], idx, torch.device("cpu"))
    st_m = ImageStack.build([a[1], b[1]], idx, torch.device("cpu"))
    bf, bm = _blur(J, 6), _blur(J, 7)
    kw = dict(max_iterations=10, tol_px=0.01, max_shift_px=2.0)

    def run(rows):
        sub = lambda bl: (bl[0][rows], bl[1][rows])  # noqa: E731
        return _fields(lsm_kernel.lsm_frames(st_f.rows(rows), st_m.rows(rows), Hf[rows], c[rows], Hm[rows],
                                             c[rows], start[rows], RADIUS, blur_f=sub(bf), blur_m=sub(bm), **kw))

    full = run(torch.arange(J))
    perm = torch.as_tensor(np.random.default_rng(0).permutation(J))
    for lo, hi in [(0, 1), (1, 9), (9, 45), (45, J)]:
        rows = perm[lo:hi]
        part = run(rows)
        for k, v in full.items():
            assert np.array_equal(v[rows.numpy()], part[k], equal_nan=True), k
    # the second pair alone, plain images
    rows = torch.arange(n_a, J)
    alone = _fields(lsm_kernel.lsm_frames(b[0], b[1], Hf[rows], c[rows], Hm[rows], c[rows], start[rows], RADIUS,
                                          blur_f=(bf[0][rows], bf[1][rows]), blur_m=(bm[0][rows], bm[1][rows]),
                                          **kw))
    for k, v in full.items():
        assert np.array_equal(v[n_a:], alone[k], equal_nan=True), k
    assert full["converged"].mean() > 0.8


def test_lsm_step_runs_the_kernel_on_the_cpu():
    """``lsm_step`` picks the kernel for CPU tensors; its accepted moves match the torch
    path's to SHIFT_TOL_PX (nearly all of them: see SAME_STOP_SHARE)."""
    from colmap_miho.refinement.config import NCCConfig
    from colmap_miho.refinement.lsm.step import lsm_step

    img1, img2, Hf, Hm, c, start = _problem("astronaut", 8)
    cfg = NCCConfig.pairwise(device="cpu", template_radius=6,
                             lsm={"enabled": True, "radius": RADIUS, "antialias": 0.5, "max_shift_px": 2.0,
                                  "tol_px": 0.01})
    calls = []
    orig = lsm_kernel.lsm_frames

    def spy(*args, **kwargs):
        calls.append(1)
        return orig(*args, **kwargs)

    lsm_kernel.lsm_frames = spy
    try:
        off_k, counts_k, ok_k = lsm_step(img1, img2, Hf, c, Hm, c, start, cfg)
    finally:
        lsm_kernel.lsm_frames = orig
    off_t, counts_t, ok_t = lsm_step(img1, img2, Hf, c, Hm, c, start, cfg, compiled=False)
    assert calls
    assert (ok_k == ok_t).float().mean() >= SAME_STOP_SHARE
    both = ok_k & ok_t
    assert ((off_k - off_t)[both].abs().amax(dim=1) < SHIFT_TOL_PX).float().mean() >= SAME_STOP_SHARE
    assert abs(counts_k["lsm_applied"] - counts_t["lsm_applied"]) <= (1 - SAME_STOP_SHARE) * len(c)


def test_torch_smoothed_reads_of_a_stack_are_per_image():
    """The torch path's smoothed reads (``blur_px``) of an ImageStack with the matches of two
    images interleaved equal each image's reads alone (the image offsets follow the matches
    when the sampler groups them by image)."""
    img1, img2, _, Hm, c, start = _problem("camera", 9)
    J = c.shape[0]
    idx = torch.as_tensor(np.arange(J) % 2)
    stack = ImageStack.build([img2, img1], idx, torch.device("cpu"))
    on, sg = _blur(J, 10)
    A = torch.eye(2, dtype=torch.float64).expand(J, 2, 2)
    both = frame_sampler(stack, Hm, c, blur_px=(on, sg))(torch.arange(J), A, start, RADIUS)
    for k, img in enumerate((img2, img1)):
        rows = torch.nonzero(idx == k)[:, 0]
        alone = frame_sampler(img, Hm[rows], c[rows], blur_px=(on[rows], sg[rows]))(
            torch.arange(rows.numel()), A[rows], start[rows], RADIUS)
        assert torch.equal(both[rows], alone)
    assert not torch.equal(both[on], frame_sampler(stack, Hm, c)(torch.arange(J), A, start, RADIUS)[on])


def test_warm_loads_the_kernel():
    assert lsm_kernel.warm()
    assert lsm_kernel.KERNELS.loaded
