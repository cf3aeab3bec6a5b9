"""A match's NCC refinement does not depend on the other matches of its call (CPU, bitwise).

The track walk refines matches in groups whose composition depends on the chunking, the
runner and the image budget; its output must be the same whatever the grouping. So each
match's result must be bitwise the same whether it is refined alone, in a batch of any size,
in any order, with any ``batch_size``, or next to matches of other image pairs in one stacked
call. Synthetic scene (no ../shared/data): a smooth random texture with a flat square, warped
by a known homography; keypoints anywhere (some too near the border to refine, some on the
flat square, some far off their match, two with a singular homography) so that every branch of ``refine_pair`` is
taken.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from colmap_miho.refinement.config import NCCConfig
from colmap_miho.refinement.ncc.correlation import ncc_maps
from colmap_miho.refinement.pairwise import RefineResult, refine_pair
from colmap_miho.refinement.warping import ImageStack, offset_grid, sample_patches
from miho_bench.variants import variant

cv2 = pytest.importorskip("cv2")

FIELDS = ("pts1", "pts2", "ncc_before", "ncc_after", "moved_side", "displacement", "rejected")
#: sizes of the sub-batches a shuffled set is cut into, one refine_pair call each
SUB_BATCHES = (1, 7, 64, 2, 33, 1, 13)


def _texture(rng, h, w):
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.6)
    img = (img - img.min()) / (img.max() - img.min())
    img[h // 2 - 30 : h // 2 + 30, w // 2 - 30 : w // 2 + 30] = 0.5  # flat: never moved
    return img


def _pair(seed, h=240, w=320, n=300):
    """(image 1, image 2, pts1, pts2, patch homography pairs (n, 2, 3, 3))."""
    rng = np.random.default_rng(seed)
    img1 = _texture(rng, h, w)
    H = np.array([[0.98, 0.05, 6.3], [-0.03, 1.01, -4.2], [3e-5, -2e-5, 1.0]])
    img2 = cv2.warpPerspective(img1, H, (w, h), flags=cv2.INTER_LINEAR)
    pts1 = rng.uniform([2.0, 2.0], [w - 3.0, h - 3.0], (n, 2))
    pts1[5:7] = [w / 2, h / 2], [w / 2 + 5, h / 2 - 4]  # on the flat square
    x = np.c_[pts1, np.ones(n)] @ H.T
    pts2 = x[:, :2] / x[:, 2:] + rng.uniform(-1.5, 1.5, (n, 2))
    pts2[::8] += rng.uniform(-14.0, 14.0, (len(pts2[::8]), 2))  # far off: border peaks
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(H)]), (n, 1, 1, 1))
    homs[[3, n // 2]] = 0.0  # singular: not refined
    return img1, img2, pts1, pts2, homs


def _assert_same(full: RefineResult, rows: np.ndarray, part: RefineResult) -> None:
    for name in FIELDS:
        a, b = getattr(full, name)[rows], getattr(part, name)
        same = np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        if not same:
            diff = np.nanmax(np.abs(a.astype(np.float64) - b)) if a.dtype.kind == "f" else None
            pytest.fail(f"{name} differs from the whole-batch call (max |diff| {diff})")


CONFIGS = {
    # the pairwise default: both directions, extended + base pass, 3 sub-pixel iterations
    "default": NCCConfig.pairwise(device="cpu"),
    # the track walk's recipe: one side moves, r = 6
    "walk": NCCConfig.pairwise(device="cpu", move="2", template_radius=6),
    # 25 template shapes chosen coarse-to-fine (per-match offsets), NCC* mask
    "paper": variant(NCCConfig.pairwise(device="cpu", template_radius=5, search_radius=4),
                     perturbations="paper", ellipse_mask=True),
    # least-squares matching after the NCC peak (bicubic samples, per-match Gauss-Newton)
    "lsm": NCCConfig.pairwise(device="cpu", move="2", template_radius=6, lsm={"enabled": True, "radius": 8}),
    # 3x3 templates: a convolution of one group would sum in another order than a batch
    "tiny": variant(NCCConfig.pairwise(device="cpu", template_radius=1, search_radius=3), min_template_std=0.0),
    # the near offsets first, the full radius only where the near peak is on its border
    "inner": NCCConfig.pairwise(device="cpu", move="2", template_radius=6, inner_radius=2),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_match_result_is_the_same_in_any_batch(name):
    cfg = CONFIGS[name]
    img1, img2, p1, p2, homs = _pair(0, n=130)
    rng = np.random.default_rng(1)
    extra = {}
    if name == "walk":  # as the walk calls it: a second candidate pair, keypoint frames
        local = homs.copy()
        local[:, 1, :2, :2] += rng.normal(0.0, 0.02, (len(p1), 2, 2))
        homs = np.stack([homs, local], axis=1)  # (N, 2 candidates, 2, 3, 3)
        extra = {"affine1": np.eye(2) + rng.normal(0.0, 0.05, (len(p1), 2, 2)),
                 "affine2": np.eye(2) + rng.normal(0.0, 0.05, (len(p1), 2, 2))}

    def call(rows, config):
        return refine_pair(img1, img2, p1[rows], p2[rows], homs[rows], config=config,
                           **{k: v[rows] for k, v in extra.items()})

    full = call(np.arange(len(p1)), cfg)
    st = full.stats
    # the scene exercises moves, rejections, flat and outside templates, singular pairs
    assert st["moved"] > 0.3 * st["n"] and st["outside"] > 0 and st["invalid_homography"] == 2
    assert full.rejected.any() and (st["gated_flat"] > 0 or cfg.min_template_std == 0)
    perm = rng.permutation(len(p1))
    # the whole set shuffled, chunked by batch_size inside one call, on one thread (the
    # whole-batch call used torch's default thread count)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        small = copy.copy(cfg)  # a copy keeps a variant's class constants
        object.__setattr__(small, "batch_size", 13)
        part = call(perm, small)
    finally:
        torch.set_num_threads(threads)
    _assert_same(full, perm, part)
    # sub-batches of mixed sizes, one call each (alone, 7, 64, ...)
    start, k = 0, 0
    while start < len(perm):
        rows = perm[start:start + SUB_BATCHES[k % len(SUB_BATCHES)]]
        _assert_same(full, rows, call(rows, cfg))
        start, k = start + rows.size, k + 1


def test_stacked_pairs_match_each_pair_alone():
    """Matches of three image pairs of different sizes in one stacked call (as the batched
    track walk makes them), and in a stack of two of them, give each pair's own results."""
    cfg = NCCConfig.pairwise(device="cpu", move="2", template_radius=6)
    pairs = [_pair(s, h, w, n=60) for s, (h, w) in enumerate([(240, 320), (200, 260), (260, 300)])]
    alone = [refine_pair(a, b, p1, p2, hm, config=cfg) for a, b, p1, p2, hm in pairs]
    dev = torch.device("cpu")
    for members in ([0, 1, 2], [2, 0]):
        index = np.concatenate([np.full(60, i) for i in range(len(members))])
        order = np.random.default_rng(len(members)).permutation(index.size)
        index = index[order]
        rows = np.concatenate([np.arange(60)] * len(members))[order]
        stack = [ImageStack.build([torch.as_tensor(pairs[m][side]) for m in members], index, dev)
                 for side in (0, 1)]
        pick = [np.stack([pairs[members[i]][f][r] for i, r in zip(index, rows, strict=True)])
                for f in (2, 3, 4)]
        res = refine_pair(stack[0], stack[1], *pick, config=cfg)
        for i, m in enumerate(members):
            sel = index == i
            got = RefineResult(*(getattr(res, f)[sel] for f in FIELDS))
            _assert_same(alone[m], rows[sel], got)


def test_patch_sampling_and_correlation_are_batch_invariant():
    """The two batched kernels on their own: each row of a batch equals that row alone."""
    rng = np.random.default_rng(2)
    img = torch.as_tensor(_texture(rng, 120, 150))
    J = 37
    H = torch.eye(3, dtype=torch.float64).repeat(J, 1, 1)
    H[:, :2, :2] += torch.as_tensor(rng.normal(0, 0.05, (J, 2, 2)))
    H[:, 2, :2] = torch.as_tensor(rng.normal(0, 1e-4, (J, 2)))
    centres = torch.as_tensor(rng.uniform(10, 110, (J, 2)))
    offsets = offset_grid(5, torch.device("cpu"))[None]
    vals, inside = sample_patches(img, H, centres, offsets)
    assert inside.sum() > J // 2
    windows = torch.as_tensor(rng.random((J, 9, 9)), dtype=torch.float32)
    templates = torch.as_tensor(rng.random((J, 2, 3, 3)), dtype=torch.float32)
    maps = ncc_maps(windows, templates)
    for j in range(J):
        one, _ = sample_patches(img, H[j:j + 1], centres[j:j + 1], offsets)
        assert torch.equal(one[0], vals[j])
        assert torch.equal(ncc_maps(windows[j:j + 1], templates[j:j + 1])[0], maps[j])
