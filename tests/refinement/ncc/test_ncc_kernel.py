"""The compiled NCC search and sub-pixel step (:mod:`colmap_miho.refinement.ncc.kernel`) against
the torch path (:func:`~colmap_miho.refinement.ncc.search.evaluate_direction`,
:func:`~colmap_miho.refinement.ncc.subpixel.iterate_subpixel`), on a perspective warp with gain and
offset of scikit-image photographs. No ../shared/data."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from colmap_miho.refinement import pairwise
from colmap_miho.refinement.config import NCCConfig
from colmap_miho.refinement.ncc import kernel as ncc_kernel
from colmap_miho.refinement.ncc import search, subpixel
from colmap_miho.refinement.ncc.correlation import ncc_maps
from colmap_miho.refinement.pairwise import refine_pair
from colmap_miho.refinement.warping import ImageStack, offset_grid, sample_values
from miho_bench.variants import variant

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")
#: samples of the kernel against grid_sample's (intensity units of [0, 1] images): the torch
#: path rounds each position to float32 grid units (about 1e-4 px on these images).
SAMPLE_TOL = 2e-4
#: the kernel's NCC maps against :func:`ncc_maps` in float64 on the same samples.
NCC_TOL = 1e-9
#: peak and centre NCC of kernel and torch path (float32 maps there), where both pick the
#: same integer peak.
PEAK_TOL = 2e-4
#: the offsets of the peaks (parabola vertices, px) where both pick the same integer peak: on
#: a share OFFSET_SHARE of them at least, and all within OFFSET_MAX_PX (a flat parabola
#: magnifies the float32 rounding of the torch path's maps).
OFFSET_TOL_PX = 2e-3
OFFSET_SHARE = 0.99
OFFSET_MAX_PX = 0.05
#: share of usable matches with the same integer peak and pass at least (the rest: near-ties,
#: and windows with flat parts, where the torch path's float32 box sums round the NCC wrong).
SAME_PEAK_SHARE = 0.97
#: the iterated sub-pixel offsets of both paths (px).
SUBPIXEL_TOL_PX = 2e-3
#: share of matches whose sub-pixel offsets agree within SUBPIXEL_TOL_PX at least.
SUBPIXEL_SHARE = 0.99
RADIUS = 6
SEARCH = 8
FLAGS = ("border", "zero", "inside", "valid", "flat")


def _gray(name: str) -> np.ndarray:
    im = getattr(skdata, name)()
    if im.ndim == 3:
        im = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(im.astype(np.float32) / 255.0, (0, 0), 1.0)


_H = np.array([[0.97, 0.06, 9.3], [-0.04, 1.02, -6.1], [4e-5, -3e-5, 1.0]])


def _pair(name: str) -> tuple[np.ndarray, np.ndarray]:
    img1 = _gray(name)
    h, w = img1.shape
    img2 = 0.9 * cv2.warpPerspective(img1, _H, (w, h), flags=cv2.INTER_LANCZOS4) + 0.05
    return img1, img2.astype(np.float32)


def _problem(name: str, J: int, seed: int):
    """Images 1 and 2 (a perspective warp of image 1), keypoints (J, 2) of each (image 2's up
    to 3 px off, some near or beyond the border) and two passes of homography pairs (the
    frame is image 1; the second pass sheared and scaled)."""
    img1, img2 = _pair(name)
    h, w = img1.shape
    rng = np.random.default_rng(seed)
    p1 = rng.uniform(-10, [w + 10, h + 10], (J, 2))
    q = np.c_[p1, np.ones(J)] @ _H.T
    p2 = q[:, :2] / q[:, 2:] + rng.uniform(-3.0, 3.0, (J, 2))
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(_H)])[None], (J, 1, 1, 1))
    shear = homs.copy()
    shear[:, 1] = np.array([[1.0, 0.12, 0.0], [0.0, 1.05, 0.0], [0.0, 0.0, 1.0]]) @ shear[:, 1]
    return img1, img2, p1, p2, [homs, shear]


def _passes(homs: list[np.ndarray], rows=slice(None)) -> list:
    grid = offset_grid(RADIUS, torch.device("cpu"))[None]
    return [(torch.tensor(h[rows]), grid, None) for h in homs]


def _cfg(**kw) -> NCCConfig:
    return NCCConfig.pairwise(template_radius=RADIUS, search_radius=SEARCH, **kw)


def _both(img_f, img_m, p_f, p_m, homs, cfg):
    win = offset_grid(RADIUS + SEARCH, torch.device("cpu"))
    args = (img_f, img_m, torch.tensor(p_f), torch.tensor(p_m), _passes(homs), 0, 1, win, cfg)
    return (search.evaluate_direction(*args, compiled=False),
            search.evaluate_direction(*args, compiled=True))


def test_samples_match_grid_sample() -> None:
    img1, img2 = _pair("camera")
    h, w = img2.shape
    ncc_kernel.KERNELS()  # the jitted helpers
    rng = np.random.default_rng(1)
    n = 60
    # centres in image 1's frame, some patches partly or wholly outside image 2
    c = rng.uniform(-20, [w + 20, h + 20], (n, 2))
    Hi = np.tile(_H, (n, 1, 1))
    R = 8
    ref, _ = sample_values(torch.tensor(img2), torch.tensor(Hi), torch.tensor(c),
                           offset_grid(R, torch.device("cpu"))[None])
    got = np.empty((n, 2 * R + 1, 2 * R + 1), np.float32)
    pos = np.empty((2, 2 * R + 1))
    for j in range(n):
        ncc_kernel._sample(img2, Hi[j], c[j, 0], c[j, 1], R, got[j], pos)
    np.testing.assert_allclose(got.reshape(n, -1), ref.reshape(n, -1).numpy(), atol=SAMPLE_TOL, rtol=0)
    assert (got == 0).any() and (got != 0).any()  # zeros outside were tested too


@pytest.mark.parametrize("so", [1, 3, 5, 17])
def test_ncc_maps_match_float64_reference(so: int) -> None:
    rng = np.random.default_rng(so)
    St = 2 * RADIUS + 1
    sw = St + so - 1
    n = 20
    win = rng.uniform(0, 1, (n, sw, sw)).astype(np.float32)
    tpl = rng.uniform(0, 1, (n, St, St)).astype(np.float32)
    win[0] = 0.25  # a flat window and a flat template: NCC 0
    tpl[1] = 0.5
    win[2, :St, :St] = 0.7  # a flat part: the offset (0, 0) is flat
    ref = ncc_maps(torch.tensor(win, dtype=torch.float64), torch.tensor(tpl, dtype=torch.float64)[:, None])
    ncc_kernel.KERNELS()
    got = np.empty((n, so, so))
    tn = np.empty((St, St))
    wc, box, cols = np.empty((sw, sw)), np.empty((2, sw + 1, sw + 1)), np.empty(so * sw * St)
    for j in range(n):
        ncc_kernel._normalize(tpl[j], tn)
        ncc_kernel._ncc(win[j], tn, so, got[j], wc, box, cols)
    np.testing.assert_allclose(got, ref[:, 0].numpy(), atol=NCC_TOL, rtol=0)
    assert (got[0] == 0).all() and (got[1] == 0).all() and got[2, 0, 0] == 0.0


@pytest.mark.parametrize(("inner", "ellipse"), [(0, False), (3, False), (3, True)])
def test_search_matches_torch(inner: int, ellipse: bool) -> None:
    img1, img2, p1, p2, homs = _problem("astronaut", 300, 0)
    ref, got = _both(torch.tensor(img1), torch.tensor(img2), p1, p2, homs,
                     variant(_cfg(inner_radius=inner), ellipse_mask=ellipse))
    for key in ("inside", "valid", "flat"):
        assert torch.equal(ref[key], got[key]), key
    usable = (ref["valid"] & ref["inside"] & ~ref["flat"]).numpy()
    assert 150 < usable.sum() < 300  # some matches outside
    # the same integer peak and pass (the offsets within a pixel, the same winning pass)
    same = ((ref["offset"] - got["offset"]).abs().amax(1) < 0.5).numpy()
    same &= ((ref["H_inv"] - got["H_inv"]).abs().flatten(1).amax(1) < 1e-9).numpy()
    assert (same & usable).sum() >= SAME_PEAK_SHARE * usable.sum()
    s = same & usable
    for key in ("peak", "centre"):
        np.testing.assert_allclose(got[key].numpy()[s], ref[key].numpy()[s], atol=PEAK_TOL, rtol=0)
    # the best separated peak: another local maximum only where two are within float32 rounding
    d2 = np.abs(got["second"].numpy()[s] - ref["second"].numpy()[s])
    assert (d2 < PEAK_TOL).mean() >= OFFSET_SHARE
    d = (got["offset"] - ref["offset"]).abs().amax(1).numpy()[s]
    assert (d < OFFSET_TOL_PX).mean() >= OFFSET_SHARE and d.max() < OFFSET_MAX_PX
    for key in ("border", "zero"):
        assert (ref[key].numpy()[s] != got[key].numpy()[s]).sum() <= 0.01 * s.sum(), key
    for key in ("frame_m", "frame_f", "H_f_inv", "H_inv"):
        np.testing.assert_allclose(got[key].numpy()[s], ref[key].numpy()[s], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(got["template"].numpy()[s], ref["template"].numpy()[s], atol=SAMPLE_TOL, rtol=0)
    assert got["peak"].dtype == ref["peak"].dtype and got["template"].dtype == ref["template"].dtype


def test_subpixel_matches_torch() -> None:
    img1, img2, p1, p2, homs = _problem("astronaut", 300, 2)
    ref, _ = _both(torch.tensor(img1), torch.tensor(img2), p1, p2, homs, _cfg())
    sel = torch.nonzero(ref["valid"] & ref["inside"] & ~ref["flat"])[:, 0]
    args = (torch.tensor(img2), ref["H_inv"][sel], ref["frame_m"][sel], ref["offset"][sel],
            ref["template"][sel], RADIUS, 3)
    a = subpixel.iterate_subpixel(*args, compiled=False)
    b = subpixel.iterate_subpixel(*args, compiled=True)
    d = (a - b).abs().amax(dim=1)
    assert (d < SUBPIXEL_TOL_PX).float().mean() >= SUBPIXEL_SHARE
    assert ((b - ref["offset"][sel]).abs().amax(dim=1) > 0.01).any()  # the step moved some
    assert torch.equal(subpixel.iterate_subpixel(*args[:-1], 0, compiled=True), args[3])


def _stack_problem(J: int):
    """Two image pairs of different sizes in ImageStacks, the jobs interleaved."""
    pa, pb = _problem("astronaut", J, 3), _problem("camera", J, 4)
    rng = np.random.default_rng(5)
    which = rng.integers(0, 2, J)
    pick = lambda a, b: np.where(which.reshape(-1, *([1] * (a.ndim - 1))) == 0, a, b)  # noqa: E731
    st_f = ImageStack.build([torch.tensor(pa[0]), torch.tensor(pb[0])], which, torch.device("cpu"))
    st_m = ImageStack.build([torch.tensor(pa[1]), torch.tensor(pb[1])], which, torch.device("cpu"))
    return st_f, st_m, pick(pa[2], pb[2]), pick(pa[3], pb[3]), [pick(a, b) for a, b in zip(pa[4], pb[4], strict=True)]


def _kernel_search(st_f, st_m, p_f, p_m, homs, rows, cfg):
    t = torch.as_tensor(rows)
    return ncc_kernel.evaluate(st_f.rows(t), st_m.rows(t), torch.tensor(p_f[rows]), torch.tensor(p_m[rows]),
                               _passes(homs, rows), 0, 1, template_radius=cfg.template_radius,
                               search_radius=cfg.search_radius, inner_radius=cfg.inner_radius,
                               ellipse_mask=cfg.ellipse_mask, min_template_std=cfg.min_template_std)


def test_each_match_independent_of_the_others() -> None:
    J = 120
    st_f, st_m, p_f, p_m, homs = _stack_problem(J)
    cfg = _cfg(inner_radius=3)
    every = _kernel_search(st_f, st_m, p_f, p_m, homs, np.arange(J), cfg)
    assert every["researched"].any() and not every["researched"].all()
    rng = np.random.default_rng(6)
    for rows in (rng.permutation(J), np.sort(rng.choice(J, 17, replace=False)), np.array([J - 1])):
        sub = _kernel_search(st_f, st_m, p_f, p_m, homs, rows, cfg)
        for key, value in sub.items():
            assert torch.equal(value, every[key][rows]), key
        t = torch.as_tensor(rows)
        off = subpixel.iterate_subpixel(st_m.rows(t), sub["H_inv"], sub["frame_m"], sub["offset"],
                                        sub["template"], RADIUS, 3, compiled=True)
        full = subpixel.iterate_subpixel(st_m, every["H_inv"], every["frame_m"], every["offset"],
                                         every["template"], RADIUS, 3, compiled=True)
        assert torch.equal(off, full[t])


def test_stack_matches_torch() -> None:
    J = 120
    st_f, st_m, p_f, p_m, homs = _stack_problem(J)
    ref, got = _both(st_f, st_m, p_f, p_m, homs, _cfg(inner_radius=3))
    usable = (ref["valid"] & ref["inside"] & ~ref["flat"]).numpy()
    for key in ("inside", "valid", "flat"):
        assert torch.equal(ref[key], got[key]), key
    close = ((ref["offset"] - got["offset"]).abs().amax(1) < OFFSET_TOL_PX).numpy()
    assert (close & usable).sum() >= SAME_PEAK_SHARE * usable.sum()


def test_inner_radius_researches_climbing_matches_over_the_full_radius() -> None:
    J = 200
    st_f, st_m, p_f, p_m, homs = _stack_problem(J)
    rows = np.arange(J)
    near = _kernel_search(st_f, st_m, p_f, p_m, homs, rows, _cfg(inner_radius=2))
    full = _kernel_search(st_f, st_m, p_f, p_m, homs, rows, _cfg())
    again = near["researched"].numpy()
    assert 0 < again.sum() < J
    usable = (near["valid"] & near["inside"] & ~near["flat"]).numpy()
    assert not (again & ~usable).any()
    for key, value in full.items():
        if key != "researched":
            assert torch.equal(near[key][again], value[again]), key
    # the others kept a peak within the smaller window
    kept = usable & ~again
    assert (near["offset"][kept].abs().amax(1) <= 2.5).all()


def test_invalid_outside_and_flat() -> None:
    img1, img2 = _pair("camera")
    img1[:100, :100] = 0.3  # a flat corner
    J = 4
    p1 = np.array([[50.0, 50.0], [-30.0, 200.0], [250.0, 250.0], [300.0, 300.0]])
    q = np.c_[p1, np.ones(J)] @ _H.T
    p2 = q[:, :2] / q[:, 2:]
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(_H)])[None], (J, 1, 1, 1))
    homs[2, 1] = 0.0  # singular
    ref, got = _both(torch.tensor(img1), torch.tensor(img2), p1, p2, [homs], _cfg(inner_radius=2))
    for key in ("inside", "valid", "flat"):
        assert torch.equal(ref[key], got[key]), key
    assert got["flat"][0] and got["inside"][0] and not got["inside"][1] and not got["valid"][2]
    assert got["valid"][3] and got["inside"][3] and not got["flat"][3]
    assert torch.equal(got["H_inv"][2], torch.eye(3, dtype=torch.float64))


def test_refine_pair_uses_the_kernel_and_agrees(monkeypatch: pytest.MonkeyPatch) -> None:
    img1, img2, p1, p2, homs = _problem("astronaut", 300, 7)
    cfg = _cfg(inner_radius=2)
    calls = []
    real = ncc_kernel.evaluate

    def spy(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(ncc_kernel, "evaluate", spy)
    got = refine_pair(img1, img2, p1, p2, homs[0], move="2", config=cfg)
    assert calls
    monkeypatch.setattr(pairwise, "evaluate_direction", functools.partial(search.evaluate_direction,
                                                                            compiled=False))
    monkeypatch.setattr(pairwise, "iterate_subpixel", functools.partial(subpixel.iterate_subpixel,
                                                                          compiled=False))
    ref = refine_pair(img1, img2, p1, p2, homs[0], move="2", config=cfg)
    assert len(calls) == 1
    same = got.moved_side == ref.moved_side
    assert same.mean() >= SAME_PEAK_SHARE and got.moved_side.any()
    both = same & (got.moved_side > 0)
    d = np.abs(got.pts2[both] - ref.pts2[both]).max(axis=1)
    assert (d < SUBPIXEL_TOL_PX).mean() >= SUBPIXEL_SHARE
