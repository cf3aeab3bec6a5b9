"""The walk's fast paths give the same bits as the plain forms they replace."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from colmap_miho.refinement import warping
from colmap_miho.refinement.ncc import correlation


def _maps(n: int, affine: bool, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([[0.02, 0.01, 0.9], [0.01, 0.02, 0.9], [3e-4, 3e-4, 0.0]],
                         dtype=torch.float64)
    M = (torch.rand(n, 3, 3, generator=g, dtype=torch.float64) - 0.5) * scale
    M[:, 2, 2] = 1.0
    if affine:
        M[:, 2, :2] = 0.0
    return M.to(torch.float32)


def _rows_grid(M32, xs, ys, affine):
    """Sample grid (n, S*S, 2) row by row: (m0 x + m1 y) + m2, divided by the clamped w."""
    n, side = M32.shape[0], xs.shape[0]

    def row(r):
        m = M32[:, r, :, None]
        v = (m[:, 0] * xs)[:, None, :] + (m[:, 1] * ys)[:, :, None]
        return (v + m[:, 2, :, None]).reshape(n, side * side)

    if affine:
        return torch.stack([row(0), row(1)], dim=-1)
    w = row(2).clamp_min(1e-6)
    return torch.stack([row(0) / w, row(1) / w], dim=-1)


@pytest.mark.parametrize("affine", [True, False])
@pytest.mark.parametrize("n,radius", [(1, 6), (5, 7), (128, 6), (40, 16)])
def test_grid_square_matches_row_by_row(affine, n, radius):
    o = warping.offset_grid(radius, torch.device("cpu")).to(torch.float32)[None]
    axes = warping._square_axes(o)
    assert axes is not None
    M32 = _maps(n, affine, seed=n + radius)
    fast = warping._grid(M32, o, axes, affine)
    general = warping._grid(M32, o, None, affine)  # no square-grid shortcut at all
    assert fast.shape == general.shape == (n, o.shape[1], 2)
    assert torch.equal(fast, _rows_grid(M32, *axes, affine))
    assert torch.equal(fast, general)


def test_grid_square_division_is_checked():
    """The non-affine form divides by w: a map with w != 1 must not be treated as affine."""
    o = warping.offset_grid(3, torch.device("cpu")).to(torch.float32)[None]
    axes = warping._square_axes(o)
    M32 = _maps(4, affine=False, seed=1)
    M32[:, 2, 0] = 0.05
    assert not torch.equal(warping._grid_square(M32, axes, True),
                           warping._grid_square(M32, axes, False))


@pytest.mark.parametrize("n", [3, 300])
def test_sample_patches_square_and_general_grids_agree(monkeypatch, n):
    """The planar square grid (a strided view for grid_sample) samples the same bits as
    the general interleaved grid, for affine and perspective maps, and for one job alone."""
    g = torch.Generator().manual_seed(7)
    image = torch.rand(60, 80, generator=g)
    H_inv = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    H_inv[:, :2, :2] += (torch.rand(n, 2, 2, generator=g, dtype=torch.float64) - 0.5) * 0.2
    H_inv[n // 2:, 2, :2] = 1e-4  # some perspective maps
    centres = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([60.0, 40.0]) + 10
    offs = warping.offset_grid(6, torch.device("cpu"))[None]
    fast, in_fast = warping.sample_patches(image, H_inv, centres, offs)
    monkeypatch.setattr(warping, "_square_axes", lambda o: None)
    plain, in_plain = warping.sample_patches(image, H_inv, centres, offs)
    assert torch.equal(fast, plain) and torch.equal(in_fast, in_plain)
    monkeypatch.undo()
    one = warping.sample_patches(image, H_inv[-1:], centres[-1:], offs)[0]
    assert torch.equal(one[0], plain[-1])
    assert plain.std() > 0.05


def _plain_ncc_maps(windows, templates, stride=1):
    """The NCC maps by the plain formula (out-of-place tail, one call for all jobs)."""
    J, K, St, _ = templates.shape
    n = St * St
    t = correlation.normalize_templates(templates)
    pad = (-J) % correlation._GROUP_PAD
    w = windows - correlation._mean64(windows)
    wp = torch.cat([w, w.new_zeros((pad,) + w.shape[1:])])
    tk = torch.cat([t, t.new_zeros((pad,) + t.shape[1:])])
    num = torch.stack([F.conv2d(wp[None], tk[:, k, None], groups=J + pad, stride=stride)[0, :J]
                       for k in range(K)], dim=1)
    s1 = correlation.box_sum(w, St)
    s2 = correlation.box_sum(w.square(), St)
    w_norm = (s2 - s1.square() / n).clamp_min(0.0).sqrt()[:, None, ::stride, ::stride]
    inv = torch.where(w_norm > 1e-6, 1.0 / w_norm.clamp_min(1e-6), 0.0)
    return (num * inv).clamp_(-1.0, 1.0)


@pytest.mark.parametrize("J,K,sw,st,stride", [(5, 1, 15, 13, 1), (300, 1, 33, 13, 1),
                                              (40, 3, 21, 9, 2), (1, 2, 23, 21, 1)])
def test_ncc_maps_match_plain_formula(monkeypatch, J, K, sw, st, stride):
    g = torch.Generator().manual_seed(J + sw)
    windows = torch.rand(J, sw, sw, generator=g)
    windows[2::4] = 0.25  # flat windows: zero maps
    templates = torch.rand(J, K, st, st, generator=g)
    templates[1::5] = 0.5  # flat templates
    # small blocks: several blocks per call
    monkeypatch.setattr(correlation, "_BLOCK_PIXELS", 16 * sw * sw)
    fast = correlation.ncc_maps(windows, templates, stride)
    plain = _plain_ncc_maps(windows, templates, stride)
    assert fast.shape == plain.shape
    assert torch.equal(fast, plain)
    assert fast.abs().amax() > 0.01  # not all flat


@pytest.mark.parametrize("max_runs", [0, 10**6])
@pytest.mark.parametrize("runs", ["consecutive", "interleaved"])
def test_sample_values_runs_and_sorted_groups_agree(monkeypatch, runs, max_runs):
    """Jobs sampled run by run and jobs sorted and gathered by image (forced by
    ``_MAX_RUNS``), in a few consecutive runs or interleaved, sample the bits of each job
    sampled alone, affine and perspective maps mixed; ``sample_patches`` gives the same
    values."""
    monkeypatch.setattr(warping, "_MAX_RUNS", max_runs)
    g = torch.Generator().manual_seed(11)
    images = [torch.rand(50, 70, generator=g), torch.rand(64, 48, generator=g)]
    n = 96
    index = (torch.arange(n) // (n // 4)) % 2 if runs == "consecutive" else torch.arange(n) % 2
    H_inv = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    H_inv[:, :2, :2] += (torch.rand(n, 2, 2, generator=g, dtype=torch.float64) - 0.5) * 0.2
    H_inv[slice(None, None, 3) if runs == "interleaved" else slice(0, 10), 2, :2] = 2e-4
    centres = torch.rand(n, 2, generator=g, dtype=torch.float64) * 30.0 + 10.0
    offs = warping.offset_grid(5, torch.device("cpu"))[None]
    stack = warping.ImageStack.build(images, index, torch.device("cpu"))
    got, good = warping.sample_values(stack, H_inv, centres, offs)
    assert bool(good.all())
    for j in range(n):
        alone, _ = warping.sample_values(images[int(index[j])], H_inv[j:j + 1], centres[j:j + 1], offs)
        assert torch.equal(got[j], alone[0])
    assert torch.equal(got, warping.sample_patches(stack, H_inv, centres, offs)[0])
    assert got.std() > 0.05
