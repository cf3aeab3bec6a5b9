"""Synthetic pair graphs with doppelganger pairs whose wrongness is known exactly.

A wall (plane z = 0, x in [0, 40] m, y in [0, 8] m, y pointing down) carries two identical
facades: facade B is facade A moved by ``FACADE_SHIFT`` along x (same points, same relief, so
the same descriptors). Context points (unique) stand in front of the wall everywhere else.
Near cameras (about 10 m from the wall, at varied heights and distances) see a third of it;
far cameras (about 22 m) see both facades.

A pair's matches: the points both images detect, except facade points whose copy is detected
too (a ratio test rejects ambiguous matches); a share of random outlier matches. A doppelganger
pair (a near camera on facade A, one on facade B) also matches each facade point of one image
to its copy in the other, as a matcher fooled by the repetition does; it is wrong when those
matches are the majority. No pair is known to be wrong any other way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WIDTH, HEIGHT, FOCAL = 640, 480, 500.0
FACADE_A = (8.0, 14.0)  # x range (m) of facade A; y in [1, 7]
FACADE_SHIFT = 18.0
NEAR_DEPTH, FAR_DEPTH = 10.0, 22.0
NEAR_X = tuple(float(x) for x in range(2, 39, 2))
FAR_X = (11.0, 15.5, 20.0, 24.5, 29.0)
MIN_MATCHES = 15


@dataclass(frozen=True)
class DoppelgangerScene:
    """Keypoints ``image -> (N, 2)`` float64 pixels, matches ``(i, j) -> int64 (M, 2)`` (i < j),
    ``wrong`` ``(i, j) -> bool`` (True for the doppelganger pairs whose wrong matches are the
    majority), the cameras' centres ``image -> (3,)`` in metres."""

    keypoints: dict[int, np.ndarray]
    matches: dict[tuple[int, int], np.ndarray]
    wrong: dict[tuple[int, int], bool]
    centres: dict[int, np.ndarray]


def _rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def make_doppelganger_scene(*, seed: int = 0, facade_points: int = 150, context_points: int = 900,
                            detect_prob: float = 0.85, noise_px: float = 0.3, outlier_share: float = 0.03,
                            fooled_prob: float = 0.6) -> DoppelgangerScene:
    """Build one scene (see the module docstring); ``fooled_prob``: chance that a pair of a
    facade-A and a facade-B near camera is matched across the facades."""
    rng = np.random.default_rng(seed)
    fa = np.column_stack([rng.uniform(*FACADE_A, facade_points), rng.uniform(1, 7, facade_points),
                          rng.uniform(-0.3, 0.0, facade_points)])
    fb = fa + [FACADE_SHIFT, 0.0, 0.0]
    ctx = np.column_stack([rng.uniform(0, 40, context_points), rng.uniform(0, 8, context_points),
                           rng.uniform(-3.0, 0.0, context_points)])
    in_facade = np.zeros(len(ctx), bool)
    for lo in (FACADE_A[0], FACADE_A[0] + FACADE_SHIFT):
        in_facade |= (ctx[:, 0] > lo) & (ctx[:, 0] < lo + FACADE_A[1] - FACADE_A[0]) & (ctx[:, 1] > 1) & (
            ctx[:, 1] < 7) & (ctx[:, 2] > -0.5)
    ctx = ctx[~in_facade]
    points = np.concatenate([fa, fb, ctx])  # facade A rows [0, F), B rows [F, 2F)
    nf = facade_points
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
    cams = [(x, NEAR_DEPTH) for x in NEAR_X] + [(x, FAR_DEPTH) for x in FAR_X]
    keypoints, point_kp, centres = {}, {}, {}
    for image, (x, depth) in enumerate(cams, start=1):
        c = np.array([x + rng.uniform(-0.5, 0.5), 4.0 + rng.uniform(-1.5, 1.5), -depth * rng.uniform(0.8, 1.2)])
        R = _rot_y(rng.uniform(-3, 3))
        cam = (points - c) @ R.T
        uv = cam[:, :2] / cam[:, 2:3] * FOCAL + K[:2, 2]
        seen = (cam[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < WIDTH) & (uv[:, 1] >= 0) & (uv[:, 1] < HEIGHT)
        seen &= rng.random(len(points)) < detect_prob
        ids = np.flatnonzero(seen)
        clutter = rng.uniform([0, 0], [WIDTH, HEIGHT], (50, 2))
        xy = np.concatenate([uv[ids] + rng.normal(0, noise_px, (len(ids), 2)), clutter])
        order = rng.permutation(len(xy))
        keypoints[image] = xy[order]
        index = np.full(len(points), -1, np.int64)
        index[ids] = np.argsort(order)[: len(ids)]
        point_kp[image], centres[image] = index, c

    def copy_of(p: np.ndarray) -> np.ndarray:
        return np.where(p < nf, p + nf, p - nf)

    facade_a_cams = [im for im, (x, d) in enumerate(cams, 1) if d == NEAR_DEPTH and FACADE_A[0] <= x <= FACADE_A[1]]
    facade_b_cams = [im for im, (x, d) in enumerate(cams, 1)
                     if d == NEAR_DEPTH and FACADE_A[0] + FACADE_SHIFT <= x <= FACADE_A[1] + FACADE_SHIFT]
    matches, wrong = {}, {}
    n_img = len(cams)
    for i in range(1, n_img + 1):
        for j in range(i + 1, n_img + 1):
            ki, kj = point_kp[i], point_kp[j]
            both = np.flatnonzero((ki >= 0) & (kj >= 0))
            facade = both < 2 * nf
            # a facade point whose copy is detected in either image is ambiguous: not matched
            amb = facade & ((ki[copy_of(both)] >= 0) | (kj[copy_of(both)] >= 0))
            good = both[~amb]
            m = [np.column_stack([ki[good], kj[good]])]
            n_bad = 0
            fooled = i in facade_a_cams and j in facade_b_cams or i in facade_b_cams and j in facade_a_cams
            if fooled and rng.random() < fooled_prob:
                src = np.flatnonzero((ki[: 2 * nf] >= 0) & (kj[copy_of(np.arange(2 * nf))] >= 0))
                src = src[(kj[src] < 0) & (ki[copy_of(src)] < 0)]  # unambiguous in both images
                m.append(np.column_stack([ki[src], kj[copy_of(src)]]))
                n_bad = len(src)
            mm = np.concatenate(m)
            n_out = int(round(outlier_share * len(mm)))
            if n_out:
                mm = np.concatenate([mm, np.column_stack([rng.integers(0, len(keypoints[i]), n_out),
                                                          rng.integers(0, len(keypoints[j]), n_out)])])
            if len(mm) >= MIN_MATCHES:
                matches[(i, j)] = mm
                wrong[(i, j)] = n_bad > len(mm) / 2
    return DoppelgangerScene(keypoints=keypoints, matches=matches, wrong=wrong, centres=centres)
