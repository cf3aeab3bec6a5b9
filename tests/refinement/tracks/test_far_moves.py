"""Far moves need evidence (``TrackConfig.far_move_check``): a periodic texture warped by a known
homography, where one period away from each true correspondence the NCC search finds a slightly
better-scoring peak (a mark that sits one period farther in the second image). Without the check
the walk takes that wrong peak; with it the keypoints stay where they were (correct)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from colmap_miho.refinement.config import NCCConfig, TrackConfig
from colmap_miho.refinement.ncc.correlation import find_peaks
from colmap_miho.refinement.tracks import refine_calls
from colmap_miho.refinement.tracks.walk import refine_tracks

PERIOD_PX = 7.0  # within the search radius (10 px), beyond the far-move bound (2 px)
W, H = 360, 280
#: image 1 -> image 2: a few degrees of rotation, 2% scale, a shift
H21 = np.array([[1.02 * np.cos(0.05), -1.02 * np.sin(0.05), 6.0],
                [1.02 * np.sin(0.05), 1.02 * np.cos(0.05), -4.0],
                [0.0, 0.0, 1.0]])


def _grid_points() -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(50.0, W - 60, 45.0), np.arange(50.0, H - 50, 45.0))
    return np.column_stack([xs.ravel(), ys.ravel()])


def _render(marks: np.ndarray, to_frame1: np.ndarray) -> np.ndarray:
    """Image whose pixel x shows the pattern at ``to_frame1 x`` (image-1 coordinates): a
    texture periodic in x and y, plus a Gaussian mark at each of ``marks`` (image 1 coords)."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    q = to_frame1 @ np.stack([xx.ravel(), yy.ravel(), np.ones(xx.size)])
    u, v = (q[:2] / q[2]).reshape(2, H, W)
    w = 2 * np.pi / PERIOD_PX
    img = 0.5 + 0.2 * np.sin(w * u) * np.cos(w * v) + 0.1 * np.cos(w * (u + v))
    for mx, my in marks:
        img += 0.35 * np.exp(-((u - mx) ** 2 + (v - my) ** 2) / (2 * 1.5 ** 2))
    return img.astype(np.float32)


def _scene():
    """Images 1 and 2 and exact matches: each keypoint's mark lies one period to its right
    in image 1 and two periods to the right in image 2 (image-1 coordinates), so the template
    of image 1 fits image 2 best one period to the right of the true position."""
    x1 = _grid_points()
    x2h = np.column_stack([x1, np.ones(len(x1))]) @ H21.T
    x2 = x2h[:, :2] / x2h[:, 2:]
    img1 = _render(x1 + [PERIOD_PX, 0.0], np.eye(3))
    img2 = _render(x1 + [2 * PERIOD_PX, 0.0], np.linalg.inv(H21))
    homs = np.stack([np.eye(3), np.linalg.inv(H21)])[None]  # (I, H^-1): A x1 ~ B x2
    idx = np.column_stack([np.arange(len(x1)), np.arange(len(x1))])
    result = SimpleNamespace(inliers=np.ones(len(x1), bool), labels=np.zeros(len(x1), np.int64),
                             patch_homographies=homs)
    return {1: img1, 2: img2}, {1: x1, 2: x2}, {(1, 2): idx}, {(1, 2): result}


@pytest.mark.parametrize("check", [False, True])
def test_walk_does_not_take_the_wrong_periodic_peak(check):
    images, kps, pm, res = _scene()
    out = refine_tracks(images, kps, pm, res, ncc_config=NCCConfig.pairwise(),
                        track_config=TrackConfig(far_move_check=check))
    # one side of each match is the anchor, the other was searched
    disp = np.concatenate([out.displacement[1], out.displacement[2]])
    err = np.concatenate([np.linalg.norm(out.keypoints[i] - kps[i], axis=1) for i in (1, 2)])
    n = len(kps[1])
    assert out.stats["refined"] == n
    if not check:  # the trap works: the search takes the peak one period away
        assert np.sum(np.abs(disp - PERIOD_PX) < 1.0) >= 0.8 * n
        assert out.stats["rejected_far"] == 0
    else:
        assert out.stats["rejected_far"] >= 0.8 * n
        assert err.max() < 1.0  # nobody moved to the wrong peak


def test_far_moves_rule():
    """Moves within the bound are free; farther ones only towards the homography's prediction."""
    n = 5
    eye = np.tile(np.eye(3), (n, 2, 1, 1))  # prediction: the fixed keypoint's own position
    pts_f = np.zeros((n, 2))
    pts_m = np.array([[0.0, 0.0], [0.0, 0.0], [6.0, 0.0], [6.0, 0.0], [0.0, 0.0]])
    new = np.array([[1.5, 0.0], [5.0, 0.0], [0.5, 0.0], [12.0, 0.0], [5.0, 0.0]])
    call = refine_calls._Call(1, 2, np.arange(n), np.arange(n), pts_f, pts_m, eye, None, None)
    moved = np.array([True, True, True, True, False])
    far = refine_calls.far_moves(call, new, moved, 2.0)
    # near the keypoint; far and away from the prediction; far but onto the prediction;
    # far and away; not moved
    assert far.tolist() == [False, True, False, True, False]
    new2 = new.copy()
    new2[3] = [3.0, 0.0]  # 3 px from the keypoint, nearer to the prediction (3 < 6): supported
    assert refine_calls.far_moves(call, new2, moved, 2.0).tolist() == [False, True, False, False, False]


def test_second_peak_and_distinctness():
    """find_peaks' second: the best local maximum two or more offsets away (shoulders of the
    best peak do not count)."""
    yy, xx = np.mgrid[-5:6, -5:6].astype(np.float32)
    bump = lambda x, y, h: h * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 2.0)  # noqa: E731
    maps = torch.tensor(np.stack([bump(3, 0, 0.9) + bump(-3, 1, 0.6), bump(0, 0, 0.8)]))[:, None]
    pk = find_peaks(maps)
    assert pk["ix"].tolist() == [3, 0] and pk["peak"][0] == pytest.approx(0.9, abs=1e-3)
    assert pk["second"][0] == pytest.approx(0.6, abs=1e-2)
    assert pk["second"][1] == pytest.approx(-1.0)  # one bump: its shoulders are no peak
