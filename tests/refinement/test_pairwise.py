"""Pairwise NCC refinement: smoke / exception / numerical tests against ground truth."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from colmap_miho.enums import Device, Perturbations, Rectification
from colmap_miho.refinement.config import NCCConfig
from colmap_miho.refinement.ncc.perturbations import perturbation_matrices
from colmap_miho.refinement.pairwise import refine_pair
from miho_bench.variants import variant

cv2 = pytest.importorskip("cv2")

# Tolerances, from what was measured (see the report in benchmarks/bench_ncc.py):
# graf img1 warped by a known homography with a sub-pixel translation, GFTT corners, side 2
# perturbed by U(-2, 2) px: median error 0.046 px after refinement (0.16 px with the paper's
# single parabola, subpixel_iterations=0).
KNOWN_MOTION_MEDIAN_PX = 0.05
SINGLE_PARABOLA_MEDIAN_PX = 0.2
# Oxford graf/boat 1->2 with GT patch homographies (I, H^-1), GT-consistent matches (< 3 px):
# measured median transfer error before -> after: graf SIFT 0.49 -> 0.26, graf GFTT 0.93 ->
# 0.30, boat SIFT 0.56 -> 0.44, boat GFTT 0.95 -> 0.47.
OXFORD_MAX_RATIO = {"sift": 0.85, "gftt": 0.6}

H_KNOWN = np.array([[1.04, 0.06, 12.37], [-0.04, 0.98, 7.71], [1.0e-5, 2.0e-5, 1.0]])


def _identity_pairs(n):
    return np.tile(np.eye(3), (n, 2, 1, 1))


@pytest.fixture(scope="module")
def known_motion(shared_data):
    """graf img1, its warp by H_KNOWN, GFTT corners and their true positions in image 2."""
    img1 = cv2.imread(str(shared_data / "oxford_affine" / "graf" / "img1.png"), cv2.IMREAD_GRAYSCALE)
    h, w = img1.shape
    img2 = cv2.warpPerspective(img1, H_KNOWN, (w, h), flags=cv2.INTER_LINEAR)
    pts1 = cv2.goodFeaturesToTrack(img1, 400, 0.01, 8).reshape(-1, 2).astype(np.float64)
    gt2 = cv2.perspectiveTransform(pts1[None], H_KNOWN)[0]
    m = 26
    inside = np.all((pts1 > m) & (pts1 < [w - m, h - m]) & (gt2 > m) & (gt2 < [w - m, h - m]), 1)
    pts1, gt2 = pts1[inside], gt2[inside]
    noisy2 = gt2 + np.random.default_rng(0).uniform(-2.0, 2.0, gt2.shape)
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(H_KNOWN)]), (len(pts1), 1, 1, 1))
    return img1, img2, pts1, gt2, noisy2, homs


def test_config_validation_names_the_field():
    for kwargs, field in [  # rectify as a dict of changes: NCCConfig.pairwise
        ({"template_radius": 0}, "template_radius"),
        ({"move": "3"}, "move"),
        ({"rectify": {"mode": "global"}}, "mode"),
        ({"device": "tpu"}, "device"),
    ]:
        with pytest.raises(ValueError, match=field):
            NCCConfig.pairwise(**kwargs)


def test_closed_choices_parse_strings_into_enums():
    """Recipes and ``--set`` give strings; the config holds the enum members (equal to them)."""
    cfg = NCCConfig.pairwise(rectify={"mode": "Local"}, device="cpu")
    assert cfg.rectify.mode is Rectification.LOCAL and cfg.rectify.mode == "local"
    assert variant(cfg, perturbations="Paper").perturbations is Perturbations.PAPER
    assert cfg.device is Device.CPU


def test_perturbation_sets():
    assert perturbation_matrices("none").shape == (1, 2, 2)
    assert perturbation_matrices("small").shape == (5, 2, 2)
    paper = perturbation_matrices("paper")
    assert paper.shape == (25, 2, 2)
    np.testing.assert_allclose(paper[0], np.eye(2))
    assert len({m.round(9).tobytes() for m in paper}) == 25
    with pytest.raises(ValueError, match="perturbations"):
        perturbation_matrices("all")


def test_bad_inputs_raise():
    img = np.zeros((50, 50), np.uint8)
    p = np.zeros((3, 2))
    with pytest.raises(ValueError, match="pts2"):
        refine_pair(img, img, p, np.zeros((2, 2)), _identity_pairs(3))
    with pytest.raises(ValueError, match="patch_homographies"):
        refine_pair(img, img, p, p, np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="image"):
        refine_pair(np.zeros((5, 5, 3)), img, p, p, _identity_pairs(3))
    with pytest.raises(ValueError, match="affine1 and affine2"):
        refine_pair(img, img, p, p, _identity_pairs(3), affine1=np.tile(np.eye(2), (3, 1, 1)))


def test_empty_input():
    img = np.zeros((30, 30), np.uint8)
    r = refine_pair(img, img, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2, 3, 3)))
    assert r.pts1.shape == (0, 2) and r.stats["n"] == 0


def test_known_motion_recovered_to_subpixel(known_motion):
    img1, img2, pts1, gt2, noisy2, homs = known_motion
    r = refine_pair(img1, img2, pts1, noisy2, homs, move="2")
    assert np.array_equal(r.pts1, pts1)
    err = np.linalg.norm(r.pts2 - gt2, axis=1)
    assert np.median(np.linalg.norm(noisy2 - gt2, axis=1)) > 1.0
    assert np.median(err) <= KNOWN_MOTION_MEDIAN_PX
    assert np.all(r.moved_side[~r.rejected & (r.moved_side > 0)] == 2)
    single = refine_pair(img1, img2, pts1, noisy2, homs, move="2",
                         config=variant(NCCConfig.pairwise(), subpixel_iterations=0))
    assert np.median(np.linalg.norm(single.pts2 - gt2, axis=1)) <= SINGLE_PARABOLA_MEDIAN_PX


def test_move_side_one_and_auto(known_motion):
    img1, img2, pts1, gt2, noisy2, homs = known_motion
    # side 1 moves: the true position of image-1 keypoints is H^-1 gt2
    noisy1 = pts1 + np.random.default_rng(1).uniform(-2.0, 2.0, pts1.shape)
    r = refine_pair(img1, img2, noisy1, gt2, homs, move="1")
    assert np.array_equal(r.pts2, gt2)
    assert np.median(np.linalg.norm(r.pts1 - pts1, axis=1)) <= 2 * KNOWN_MOTION_MEDIAN_PX
    # auto: at most one side changes per match, consistent with moved_side
    ra = refine_pair(img1, img2, pts1, noisy2, homs, move="auto")
    c1 = np.any(ra.pts1 != pts1, axis=1)
    c2 = np.any(ra.pts2 != noisy2, axis=1)
    assert not np.any(c1 & c2)
    assert np.array_equal(c1, ra.moved_side == 1) and np.array_equal(c2, ra.moved_side == 2)
    residual = np.linalg.norm(
        cv2.perspectiveTransform(ra.pts1[None], H_KNOWN)[0] - ra.pts2, axis=1
    )
    assert np.median(residual) <= 2 * KNOWN_MOTION_MEDIAN_PX


def test_input_types_agree(known_motion):
    img1, img2, pts1, gt2, noisy2, homs = known_motion
    sl = slice(0, 40)
    a = refine_pair(img1, img2, pts1[sl], noisy2[sl], homs[sl], move="2")
    b = refine_pair(torch.from_numpy(img1.astype(np.float32) / 255), img2.astype(np.float64) / 255,
                    torch.from_numpy(pts1[sl]), noisy2[sl], torch.from_numpy(homs[sl]), move="2",
                    config=NCCConfig.pairwise(batch_size=7))
    np.testing.assert_allclose(a.pts2, b.pts2, atol=1e-4)
    # a homography pair scaled by -1 is the same pair
    c = refine_pair(img1, img2, pts1[sl], noisy2[sl], -homs[sl], move="2")
    np.testing.assert_allclose(a.pts2, c.pts2, atol=1e-6)


def test_flat_patches_do_not_move():
    rng = np.random.default_rng(0)
    img = np.full((120, 120), 0.5) + rng.normal(0, 0.002, (120, 120))
    pts = rng.uniform(40, 80, (20, 2))
    r = refine_pair(img, img, pts, pts + 0.7, _identity_pairs(20))
    assert r.stats["gated_flat"] == 20 and not r.moved_side.any()
    np.testing.assert_array_equal(r.pts2, pts + 0.7)


def _edge_image(x0=60.3, size=120):
    """A smooth vertical step edge at x = x0 (intensity 0.2 -> 0.8)."""
    x = np.arange(size)[None, :].repeat(size, 0)
    return 0.5 + 0.3 * np.tanh((x - x0) / 1.5)


def test_edge_patches_move_only_across_the_edge():
    img = _edge_image()
    ys = np.linspace(40, 80, 15)
    pts1 = np.stack([np.full_like(ys, 60.3), ys], 1)
    pts2 = pts1 + [1.6, 1.3]  # off the edge by 1.6 px, along it by 1.3 px
    star = refine_pair(img, img, pts1, pts2, _identity_pairs(15), move="2",
                       config=variant(NCCConfig.pairwise(), ellipse_mask=True))
    moved = star.moved_side == 2
    assert moved.sum() >= 10
    np.testing.assert_allclose(star.pts2[moved, 0], 60.3, atol=0.05)  # back onto the edge
    np.testing.assert_allclose(star.pts2[:, 1], pts2[:, 1], atol=1e-9)  # not along it


@pytest.mark.parametrize("detector", ["sift", "gftt"])
def test_oxford_real_pairs_with_gt_homography(shared_data, detector):
    from miho_bench.datasets import oxford_pairs
    from miho_bench.frontend import sift_matches
    from miho_bench.match_errors import transfer_error

    pair = oxford_pairs(shared_data / "oxford_affine" / "graf", targets=(2,))[0]
    img1, img2 = pair.image1(), pair.image2()
    fm = sift_matches(img1, img2, detector=detector, max_features=2000)
    before = transfer_error(pair.H_2from1, fm.pts1, fm.pts2)
    good = before < 3.0
    assert good.sum() >= 50
    p1, p2 = fm.pts1[good], fm.pts2[good]
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(pair.H_2from1)]), (len(p1), 1, 1, 1))
    r = refine_pair(img1, img2, p1, p2, homs)
    after = transfer_error(pair.H_2from1, r.pts1, r.pts2)
    assert np.median(after) <= OXFORD_MAX_RATIO[detector] * np.median(before[good])


def test_example_refine_pair_runs(shared_data, monkeypatch, capsys):
    import runpy

    monkeypatch.setenv("COLMAP_MIHO_DATA", str(shared_data))
    example = Path(__file__).resolve().parents[2] / "examples" / "refine_pair.py"
    main = runpy.run_path(str(example))["main"]
    assert main(["graf", "2", "gftt"]) == 0
    out = capsys.readouterr().out
    before, after = (float(x) for x in re.search(r"([\d.]+) px -> ([\d.]+) px", out).groups())
    assert after < before


def test_base_pass_uses_keypoint_affine_frames(known_motion):
    """Extended pair useless (a 25-degree rotation); the base pass with the true local affine
    frames (image-2 frame = Jacobian of H at the keypoint) still recovers the motion."""
    img1, img2, pts1, gt2, noisy2, _ = known_motion
    sl = slice(0, 120)
    p1, g2, n2 = pts1[sl], gt2[sl], noisy2[sl]
    c, s = np.cos(np.radians(25)), np.sin(np.radians(25))
    wrong = np.tile(np.stack([np.eye(3), np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])]),
                    (len(p1), 1, 1, 1))
    x = np.c_[p1, np.ones(len(p1))] @ H_KNOWN.T
    w = x[:, 2]
    jac = (H_KNOWN[None, :2, :2] - (x[:, :2] / w[:, None])[:, :, None] * H_KNOWN[None, 2:, :2]) / w[:, None, None]
    without = refine_pair(img1, img2, p1, n2, wrong, move="2",
                          config=variant(NCCConfig.pairwise(), use_base_pair=False))
    with_aff = refine_pair(img1, img2, p1, n2, wrong, move="2",
                           affine1=np.tile(np.eye(2), (len(p1), 1, 1)), affine2=jac)
    e_without = np.median(np.linalg.norm(without.pts2 - g2, axis=1))
    e_with = np.median(np.linalg.norm(with_aff.pts2 - g2, axis=1))
    assert e_with <= KNOWN_MOTION_MEDIAN_PX and e_without > 2 * e_with


def test_result_of_a_match_does_not_depend_on_its_batch(known_motion):
    """Bitwise on the CPU: the pipeline refines tracks in several processes with different
    batches. (CUDA kernels round differently per batch shape: see the test below.)"""
    img1, img2, pts1, gt2, noisy2, homs = known_motion
    full = refine_pair(img1, img2, pts1, noisy2, homs,
                       config=NCCConfig.pairwise(batch_size=64, device="cpu"))
    part = refine_pair(img1, img2, pts1[5:45], noisy2[5:45], homs[5:45],
                       config=NCCConfig.pairwise(batch_size=13, device="cpu"))
    np.testing.assert_array_equal(full.pts1[5:45], part.pts1)
    np.testing.assert_array_equal(full.pts2[5:45], part.pts2)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("perturbations", ["none", "paper"])
def test_cuda_agrees_with_cpu(known_motion, perturbations):
    """Same moves on CUDA as on the CPU, to float32 rounding (measured on an H100: at most
    6e-4 px, median 2e-6 px; benchmarks/check_cuda.py). One side moves, so that near-ties
    between the two directions cannot flip the side."""
    img1, img2, pts1, gt2, noisy2, homs = known_motion
    res = {dev: refine_pair(img1, img2, pts1, noisy2, homs, move="2",
                            config=variant(NCCConfig.pairwise(device=dev), perturbations=perturbations))
           for dev in ("cpu", "cuda")}
    assert res["cuda"].stats["device"].startswith("cuda")
    agree = res["cpu"].moved_side == res["cuda"].moved_side
    assert agree.mean() >= 0.99
    diff = np.linalg.norm(res["cpu"].pts2 - res["cuda"].pts2, axis=1)[agree]
    assert np.median(diff) < 1e-4 and np.percentile(diff, 99) < 1e-2


def test_image_stack_samples_like_separate_images():
    """Jobs reading images of different sizes from one padded stack get the values and the
    inside flags of sampling each image on its own, bitwise, patches crossing the border
    included (the batched track walk relies on it)."""
    from colmap_miho.refinement.warping import ImageStack, offset_grid, sample_patches

    rng = np.random.default_rng(0)
    images = [torch.as_tensor(rng.random((60, 90)), dtype=torch.float32),
              torch.as_tensor(rng.random((80, 50)), dtype=torch.float32),
              torch.as_tensor(rng.random((40, 40)), dtype=torch.float32)]
    index = np.array([0, 1, 2, 1, 0, 2])
    # centres near each image's far corner: some patches cross that image's border, which the
    # padding of the larger images must not hide
    centres = torch.tensor([[87.0, 50.0], [30.0, 40.0], [20.0, 20.0], [47.0, 70.0],
                            [10.0, 10.0], [37.0, 30.0]], dtype=torch.float64)
    H = torch.eye(3, dtype=torch.float64).repeat(6, 1, 1)
    H[:, 0, 1] = 0.05
    offsets = offset_grid(4, torch.device("cpu"))[None]
    stack = ImageStack.build(images, index, torch.device("cpu"))
    got, inside = sample_patches(stack, H, centres, offsets)
    for j, k in enumerate(index):
        want, want_in = sample_patches(images[k], H[j:j + 1], centres[j:j + 1], offsets)
        assert bool(inside[j]) == bool(want_in[0])
        np.testing.assert_array_equal(got[j].numpy(), want[0].numpy())
    assert inside.tolist() == [False, True, True, False, True, False]
