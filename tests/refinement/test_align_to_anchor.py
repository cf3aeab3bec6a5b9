"""One reference per track (``TrackConfig.align_to_anchor``): a keypoint two or more matches
away from its track's anchor is aligned to the anchor's patch through the chained patch
homography pairs, so the errors of the keypoints between do not add up. Fake refiner, no
images needed."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from colmap_miho.refinement.config import TrackConfig
from colmap_miho.refinement.ncc import RefineResult
from colmap_miho.refinement.tracks import refine_tracks

#: error (pixels, x) the fake refiner adds to every keypoint it aligns.
CALL_ERROR_PX = 0.25
#: tolerance of the transfer (pixels): float64 products of 3x3 matrices.
TRANSFER_TOL_PX = 1e-9


def _translation(dx: float, dy: float) -> np.ndarray:
    h = np.eye(3)
    h[:2, 2] = dx, dy
    return h


def _affine(a: float, b: float, c: float, d: float, dx: float, dy: float) -> np.ndarray:
    return np.array([[a, b, dx], [c, d, dy], [0.0, 0.0, 1.0]])


# true maps image 1 -> image k (pixels): a chain 1-2, 2-3, 3-4 of matched pairs
TO = {1: np.eye(3), 2: _affine(1.1, 0.05, -0.02, 0.95, 12.0, -3.0),
      3: _affine(0.9, -0.1, 0.08, 1.05, -7.0, 20.0), 4: _affine(1.2, 0.0, 0.0, 1.2, 5.0, 5.0)}
X1 = np.array([100.0, 80.0])


def _apply(h: np.ndarray, x: np.ndarray) -> np.ndarray:
    v = h @ np.r_[x, 1.0]
    return v[:2] / v[2]


class TransferRefiner:
    """Moves each moving keypoint to the transfer of the fixed one through the homography
    pair (``B x_m ~ A x_f``), plus ``CALL_ERROR_PX`` in x: an aligner with a fixed error per
    call. Records every call's fixed positions."""

    def __init__(self) -> None:
        self.fixed: list[np.ndarray] = []

    def __call__(self, image1, image2, pts1, pts2, homs, *, move, config, **kw):
        pts1, pts2, homs = np.asarray(pts1, float), np.asarray(pts2, float), np.asarray(homs)
        if homs.ndim == 5:
            homs = homs[:, 0]
        self.fixed.append(pts1.copy())
        new = np.array([_apply(np.linalg.solve(h[1], h[0]), p) for h, p in zip(homs, pts1, strict=True)])
        new[:, 0] += CALL_ERROR_PX
        n = len(pts1)
        return RefineResult(pts1=pts1.copy(), pts2=new, ncc_before=np.zeros(n), ncc_after=np.ones(n),
                            moved_side=np.full(n, 2, np.int8),
                            displacement=np.linalg.norm(new - pts2, axis=1),
                            rejected=np.zeros(n, bool), stats={})


def _chain():
    """Images 1..5 with one keypoint each, matched 1-2, 2-3, 3-4 and 2-5 (anchor: image 2,
    the most connected), keypoints 2 px off their true positions, each pair's homography
    pair (I, true map first -> second)^-1 in the pair's orientation."""
    to = {**TO, 5: _affine(1.0, 0.0, 0.0, 1.0, -30.0, 4.0)}
    kps = {i: (_apply(to[i], X1) + 2.0)[None] for i in to}
    pm = {(1, 2): np.array([[0, 0]]), (2, 3): np.array([[0, 0]]), (3, 4): np.array([[0, 0]]),
          (2, 5): np.array([[0, 0]])}
    results = {}
    for (a, b), m in pm.items():
        h_ab = to[b] @ np.linalg.inv(to[a])  # image a -> image b
        results[(a, b)] = SimpleNamespace(inliers=np.ones(len(m), bool), labels=np.zeros(len(m), np.int64),
                                          patch_homographies=np.stack([np.eye(3), np.linalg.inv(h_ab)])[None])
    return to, kps, pm, results


def test_far_keypoints_are_aligned_to_the_anchor_through_the_chain():
    to, kps, pm, results = _chain()
    images = {i: np.zeros((4, 4)) for i in kps}
    partner = refine_tracks(images, kps, pm, results, refine_fn=TransferRefiner())
    fake = TransferRefiner()
    anchor = refine_tracks(images, kps, pm, results, refine_fn=fake,
                           track_config=TrackConfig(align_to_anchor=True))
    # image 4 is two matches from the anchor (image 2): aligned to image 3 by default, to
    # the anchor with the option
    assert partner.refined_against[4][0].tolist() == [3, 0]
    assert anchor.refined_against[4][0].tolist() == [2, 0]
    assert partner.stats["refined_against_moved"] == 1
    assert anchor.stats["refined_against_moved"] == 0
    # one call's error, not two: the chained pair transfers the anchor exactly
    truth4 = _apply(to[4] @ np.linalg.inv(to[2]), kps[2][0])
    err_anchor = anchor.keypoints[4][0] - truth4
    err_partner = partner.keypoints[4][0] - truth4
    assert np.allclose(err_anchor, [CALL_ERROR_PX, 0.0], atol=TRANSFER_TOL_PX)
    assert abs(err_partner[0]) > 1.5 * CALL_ERROR_PX  # the partner's own error is added
    # level-1 keypoints are the same either way
    for i in (1, 3, 5):
        assert np.array_equal(anchor.keypoints[i], partner.keypoints[i])
    # the second level's call read the anchor's position as the fixed side
    assert any(np.array_equal(f, kps[2]) for f in fake.fixed[1:])


def test_level_one_walk_is_unchanged_and_default_is_off():
    """A star (every keypoint matched to the anchor) walks the same with and without the
    option; the default leaves it off."""
    assert TrackConfig().align_to_anchor is False
    to, kps, pm, results = _chain()
    star = {p: m for p, m in pm.items() if 2 in p}
    res = {p: results[p] for p in star}
    images = {i: np.zeros((4, 4)) for i in kps}
    a = refine_tracks(images, kps, star, res, refine_fn=TransferRefiner())
    b = refine_tracks(images, kps, star, res, refine_fn=TransferRefiner(),
                      track_config=TrackConfig(align_to_anchor=True))
    for i in a.keypoints:
        assert np.array_equal(a.keypoints[i], b.keypoints[i])
        assert np.array_equal(a.refined_against[i], b.refined_against[i])


def test_per_pair_calls_give_the_batched_result():
    to, kps, pm, results = _chain()
    images = {i: np.zeros((4, 4)) for i in kps}
    out = [refine_tracks(images, kps, pm, results, refine_fn=TransferRefiner(),
                         track_config=TrackConfig(align_to_anchor=True, batch_pairs=b))
           for b in (True, False)]
    for i in kps:
        assert np.array_equal(out[0].keypoints[i], out[1].keypoints[i])
