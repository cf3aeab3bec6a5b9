"""Joint multi-photo LSM (:mod:`colmap_miho.refinement.tracks.multiphoto`) on scikit-image photographs.

A track is a reference view (the photograph) and 3 views of it under known affine maps with
gain and offset. The maps handed to the step are off by a further small affine (what LSM's A
absorbs) and the start positions by up to 0.5 px (what the shift absorbs). No ../shared/data
needed.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from colmap_miho.refinement.config import NCCConfig, TrackConfig
from colmap_miho.refinement.tracks.multiphoto import MULTIPHOTO_COUNTERS, joint_lsm
from colmap_miho.refinement.warping import ImageStack, to_frame

cv2 = pytest.importorskip("cv2")
skdata = pytest.importorskip("skimage.data")

#: median error (px) of the recovered positions without noise.
MEDIAN_TOL_PX = 0.02
#: with image noise, the joint step's median and mean error are at most this factor of the
#: star of pairwise alignments' (each view against the reference alone) on the same
#: observations. With the reference fixed, each view's error at the joint fixed point is, to
#: first order, its own noise less the reference's, as in the star, so the two are expected
#: equal up to non-linear effects.
NOISY_RATIO = 1.1
#: image noise (standard deviation, intensities in [0, 1]) of the noisy test.
NOISE = 0.01
#: Gauss-Newton tolerance (px) of the noisy test (as the LSM recipe: noise-limited shifts).
NOISY_TOL_PX = 0.01
RADIUS = 8
ITERATIONS = 3

_VIEWS = [  # (rotation deg, sx, sy, tx, ty, gain, offset): view = gain * ref(M^-1 x) + offset
    (8, 1.08, 0.97, 15.2, -9.7, 0.8, 0.10),
    (-6, 0.93, 1.05, -12.6, 7.3, 1.2, -0.05),
    (3, 1.02, 1.10, 6.4, 11.9, 0.9, 0.05),
]


def _gray(name: str) -> np.ndarray:
    im = getattr(skdata, name)()
    if im.ndim == 3:
        im = cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(im.astype(np.float32) / 255.0, (0, 0), 1.0)


def _affine(rot: float, sx: float, sy: float, tx: float, ty: float) -> np.ndarray:
    th = np.deg2rad(rot)
    return np.array([[sx * np.cos(th), -sy * np.sin(th), tx], [sx * np.sin(th), sy * np.cos(th), ty],
                     [0, 0, 1]])


def _track_problem(name: str, *, noise: float, seed: int, flat: bool = False):
    """(images (D,), stack index inputs, H_inv (N, 3, 3), centres (N, 2), track (N,),
    is_ref (N,), true positions (N, 2)) for tracks of 4 observations at corners of the
    photograph (or at points of a flat square pasted into every view, ``flat``)."""
    rng = np.random.default_rng(seed)
    ref = _gray(name).copy()
    h, w = ref.shape
    if flat:
        ref[h // 2 - 60:h // 2 + 60, w // 2 - 60:w // 2 + 60] = 0.5
        pts = np.array([[w / 2 + dx, h / 2 + dy] for dx in (-20, 0, 20) for dy in (-20, 20)], float)
    else:
        pts = cv2.goodFeaturesToTrack((ref * 255).astype(np.uint8), 200, 0.01, 8).reshape(-1, 2)
        m = 60
        pts = pts[(pts[:, 0] > m) & (pts[:, 0] < w - m) & (pts[:, 1] > m) & (pts[:, 1] < h - m)]
        pts = pts.astype(np.float64)
    images = [ref + rng.normal(0, noise, ref.shape).astype(np.float32)]
    maps = [np.eye(3)]
    for rot, sx, sy, tx, ty, gain, off in _VIEWS:
        M = _affine(rot, sx, sy, tx, ty)
        view = gain * cv2.warpAffine(ref, M[:2], (w, h), flags=cv2.INTER_LANCZOS4) + off
        images.append((view + rng.normal(0, noise, ref.shape)).astype(np.float32))
        maps.append(M)
    J, V = len(pts), len(maps)
    H_inv, centres, track, is_ref, truth, index = [], [], [], [], [], []
    for j, p in enumerate(pts):
        for v, M in enumerate(maps):
            true = (M @ np.append(p, 1.0))[:2]
            H = M.copy()
            if v:  # a rectification off by a small affine, a start off by up to 0.5 px
                Q = np.eye(3)
                Q[:2, :2] += rng.uniform(-0.04, 0.04, (2, 2))
                H = M @ Q
                start = true + rng.uniform(-0.5, 0.5, 2)
                H[:2, 2] += start - (H @ np.append(p, 1.0))[:2]
            H_inv.append(H)
            centres.append(p)
            track.append(j)
            is_ref.append(v == 0)
            truth.append(true)
            index.append(v)
    assert len(truth) == J * V
    return ([torch.from_numpy(im) for im in images], np.array(index), torch.tensor(np.array(H_inv)),
            torch.tensor(np.array(centres)), torch.tensor(track), torch.tensor(is_ref),
            np.array(truth))


def _errors(problem, cfg: NCCConfig, *, star: bool = False) -> tuple[np.ndarray, np.ndarray, object]:
    """Position errors (px) and acceptance of the non-reference observations, and the result;
    ``star``: each view aligned to the reference alone (tracks of 2: the pairwise LSM)."""
    images, index, H_inv, centres, track, is_ref, truth = problem
    if star:  # split each track into reference + one view: the template is the reference
        V = int((track == 0).sum())
        rows = [r for j in range(int(track.max()) + 1) for v in range(1, V)
                for r in (j * V, j * V + v)]
        sel = torch.tensor(rows)
        index, H_inv, centres, is_ref, truth = index[rows], H_inv[sel], centres[sel], is_ref[sel], truth[rows]
        track = torch.arange(len(rows)) // 2
    stack = ImageStack.build(images, index, torch.device("cpu"))
    # from a start up to 0.5 px off (not the walk's): the star pass first
    res = joint_lsm(stack, H_inv, centres, track, is_ref, cfg, ITERATIONS, star_first=True)
    new = to_frame(H_inv, centres + res.shift).numpy()
    mov = ~is_ref.numpy()
    return np.linalg.norm(new - truth, axis=1)[mov], res.accepted.numpy()[mov], res


def _cfg(tol_px: float = 0.001) -> NCCConfig:
    return NCCConfig.pairwise(lsm={"enabled": True, "radius": RADIUS, "max_shift_px": 2.0, "tol_px": tol_px,
                                   "antialias": 0.0})


@pytest.mark.parametrize("name", ["camera", "astronaut"])
def test_joint_recovers_known_positions(name: str) -> None:
    problem = _track_problem(name, noise=0.0, seed=1)
    err, acc, res = _errors(problem, _cfg())
    err = err[acc]
    n_mov = int((~problem[5]).sum())
    assert res.counts["joint_applied"] >= 0.8 * n_mov
    assert sum(res.counts.values()) == n_mov
    assert np.median(err) < MEDIAN_TOL_PX
    assert not res.accepted[problem[5]].any()  # references never move
    assert float(res.shift[problem[5]].abs().max()) == 0.0


@pytest.mark.parametrize("name", ["camera", "astronaut"])
def test_joint_not_worse_than_star_with_noise(name: str) -> None:
    """Same observations, accepted by both: the joint step against the star of pairwise
    alignments, with image noise in every view."""
    problem = _track_problem(name, noise=NOISE, seed=2)
    joint, acc_j, _ = _errors(problem, _cfg(NOISY_TOL_PX))
    star, acc_s, _ = _errors(problem, _cfg(NOISY_TOL_PX), star=True)
    both = acc_j & acc_s
    assert both.sum() >= 0.8 * both.size
    assert np.median(joint[both]) <= NOISY_RATIO * np.median(star[both])
    assert np.mean(joint[both]) <= NOISY_RATIO * np.mean(star[both])


def test_flat_patches_rejected() -> None:
    problem = _track_problem("camera", noise=0.002, seed=3, flat=True)
    _, _, res = _errors(problem, _cfg())
    assert not res.accepted.any()
    assert res.counts["joint_applied"] == 0


def test_anti_aliased_joint_still_recovers() -> None:
    """With the coarsest-view blur on (all views here within 10% of the reference's scale,
    the blur hits the finer ones), positions stay within the tolerance."""
    problem = _track_problem("camera", noise=0.0, seed=4)
    err, acc, _ = _errors(problem, NCCConfig.pairwise(lsm={"enabled": True, "radius": RADIUS, "max_shift_px": 2.0,
                                                           "tol_px": 0.001, "antialias": 0.5}))
    assert np.median(err[acc]) < 2 * MEDIAN_TOL_PX


def test_config_defaults_and_counters() -> None:
    assert TrackConfig().multiphoto_lsm is False
    for bad in (0, 11):
        with pytest.raises(ValueError, match="multiphoto_iterations"):
            TrackConfig(multiphoto_iterations=bad)
    assert MULTIPHOTO_COUNTERS[0] == "joint_tracks"


# --- the pass after the walk -------------------------------------------------------------

#: error (pixels, x) the fake walk refiner adds to every keypoint it aligns.
CALL_ERROR_PX = 0.25
#: without the star pass, the consensus passes leave at most this share of the walk's error.
PARTWAY_FACTOR = 0.7
#: true maps image 2 (the photograph) -> image k (pixels): matched pairs 1-2, 2-3, 3-4, 2-5; anchor image 2.
#: The anchor's image is the photograph itself: its patch is then read from the photograph,
#: not from a resampled copy whose interpolation error every view would share.
_TO = {1: _affine(4, 1.05, 0.97, 12.0, -3.0), 2: np.eye(3), 3: _affine(-5, 0.95, 1.04, -7.0, 10.0),
       4: _affine(2, 1.08, 1.08, 5.0, 5.0), 5: _affine(-3, 1.0, 1.0, -9.0, 4.0)}


def _apply(h: np.ndarray, x: np.ndarray) -> np.ndarray:
    v = h @ np.r_[x, 1.0]
    return v[:2] / v[2]


class _TransferRefiner:
    """Moves each moving keypoint to the transfer of the fixed one through the homography
    pair, plus ``CALL_ERROR_PX`` in x: a walk whose every alignment is off by that much."""

    def __call__(self, image1, image2, pts1, pts2, homs, *, move, config, **kw):
        from colmap_miho.refinement.pairwise import RefineResult

        pts1, pts2, homs = np.asarray(pts1, float), np.asarray(pts2, float), np.asarray(homs)
        if homs.ndim == 5:
            homs = homs[:, 0]
        new = np.array([_apply(np.linalg.solve(h[1], h[0]), p) for h, p in zip(homs, pts1, strict=True)])
        new[:, 0] += CALL_ERROR_PX
        n = len(pts1)
        return RefineResult(pts1=pts1.copy(), pts2=new, ncc_before=np.zeros(n), ncc_after=np.ones(n),
                            moved_side=np.full(n, 2, np.int8), displacement=np.linalg.norm(new - pts2, axis=1),
                            rejected=np.zeros(n, bool), stats={})


def test_pass_after_the_walk_moves_every_observation_to_the_anchor() -> None:
    """Tracks of 5 views of the photograph, walked by a refiner off by 0.25 px per call (0.5
    px two matches from the anchor); the joint pass, on the images, brings every observation
    to the anchor keypoint's true transfer, and records the anchor as its reference."""
    from types import SimpleNamespace

    from colmap_miho.refinement.tracks.walk import refine_tracks

    ref = _gray("camera")
    h, w = ref.shape
    pts = cv2.goodFeaturesToTrack((ref * 255).astype(np.uint8), 60, 0.01, 10).reshape(-1, 2)
    pts = pts[(pts.min(axis=1) > 150) & (pts.max(axis=1) < 350)].astype(np.float64)
    images = {k: cv2.warpAffine(ref, M[:2], (w, h), flags=cv2.INTER_LANCZOS4) for k, M in _TO.items()}
    # the anchor's keypoints on pixel centres (its patch is read unresampled), the others off
    kps = {k: np.array([_apply(M, p) for p in pts]) + (0.0 if k == 2 else 0.3) for k, M in _TO.items()}
    pm, results = {}, {}
    for a, b in ((1, 2), (2, 3), (3, 4), (2, 5)):
        h_ab = _TO[b] @ np.linalg.inv(_TO[a])
        pm[(a, b)] = np.stack([np.arange(len(pts))] * 2, axis=1)
        results[(a, b)] = SimpleNamespace(inliers=np.ones(len(pts), bool), labels=np.zeros(len(pts), np.int64),
                                          patch_homographies=np.stack([np.eye(3), np.linalg.inv(h_ab)])[None])
    ncc = NCCConfig.pairwise(lsm={"enabled": True, "radius": RADIUS, "max_shift_px": 2.0, "tol_px": 0.001})
    walk = refine_tracks(images, kps, pm, results, refine_fn=_TransferRefiner(), ncc_config=ncc)
    # 3 consensus passes from this (poor) walk go part of the way (the star pass that went all
    # of it from such a start is joint_lsm's star_first, tested above; the walk starts aligned)
    out = refine_tracks(images, kps, pm, results, refine_fn=_TransferRefiner(), ncc_config=ncc,
                        track_config=TrackConfig(multiphoto_lsm=True))
    assert out.stats["joint_tracks"] == len(pts)
    assert out.stats["joint_observations"] == 4 * len(pts)
    assert out.stats["joint_applied"] >= 0.9 * 4 * len(pts)
    assert np.array_equal(out.keypoints[2], kps[2])  # the anchor image's keypoints stay
    for k in (1, 3, 4, 5):
        truth = np.array([_apply(_TO[k] @ np.linalg.inv(_TO[2]), p) for p in kps[2]])
        err_walk = np.linalg.norm(walk.keypoints[k] - truth, axis=1)
        err = np.linalg.norm(out.keypoints[k] - truth, axis=1)
        assert np.median(err_walk) > 0.9 * CALL_ERROR_PX
        assert np.median(err) < PARTWAY_FACTOR * np.median(err_walk)
        moved = out.displacement[k] > 0
        assert (out.refined_against[k][moved, 0] == 2).all()
        assert np.array_equal(out.refined_against[k][moved, 1], np.flatnonzero(moved))
