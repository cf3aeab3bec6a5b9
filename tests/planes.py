"""Tiny synthetic scenes for filter tests: planted planes seen by two pinhole cameras.

Pixel convention: (x, y), integer = pixel centre. Everything is driven by the given
``numpy.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WIDTH, HEIGHT = 800, 600
K = np.array([[700.0, 0, 399.5], [0, 700.0, 299.5], [0, 0, 1]])


@dataclass
class PlaneScene:
    """``x1``, ``x2`` ``(N, 2)`` matches; ``plane`` int ``(N,)`` planted plane or -1 for an
    outlier; ``H`` ``(P, 3, 3)`` ground-truth ``H_2from1`` of each plane (after ``transform``)."""

    x1: np.ndarray
    x2: np.ndarray
    plane: np.ndarray
    H: np.ndarray

    @property
    def is_inlier(self) -> np.ndarray:
        return self.plane >= 0


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    a = np.deg2rad(deg)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def image2_transform(rotate_deg: int = 0, mirror: bool = False) -> np.ndarray:
    """3x3 map applied to image-2 pixels: rotation by a multiple of 90 degrees about the image
    centre, after an optional left-right mirror."""
    c = np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2])
    M = np.diag([-1.0, 1.0]) if mirror else np.eye(2)
    a = np.deg2rad(rotate_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).round(12) @ M
    G = np.eye(3)
    G[:2, :2] = R
    G[:2, 2] = c - R @ c
    return G


def make_scene(rng: np.random.Generator, *, n_planes: int = 3, per_plane: int = 150,
               outlier_ratio: float = 0.4, noise: float = 0.5, rotate_deg: int = 0,
               mirror: bool = False, baseline: float = 0.8) -> PlaneScene:
    """Planes occupying vertical strips of image 1, seen from a second camera turned by ~10
    degrees and moved by ``baseline`` (plane depths 5-9); ``outlier_ratio`` of all matches are
    random pairs; Gaussian ``noise`` px."""
    R = _rot(np.array([0.2, 1.0, 0.1]), 10.0)
    t = np.array([-1.0, 0.125, 0.125]) * baseline
    G = image2_transform(rotate_deg, mirror)
    Kinv = np.linalg.inv(K)
    x1s, x2s, labels, Hs = [], [], [], []
    edges = np.linspace(20, WIDTH - 20, n_planes + 1)
    for p in range(n_planes):
        normal = _rot(np.array([1.0, 0.3, 0.0]), rng.uniform(-35, 35)) @ np.array([0, 0, 1.0])
        depth = rng.uniform(5, 9)
        H = K @ (R + np.outer(t, normal) / depth) @ Kinv  # plane n.X = depth in camera 1
        H = G @ H
        Hs.append(H / H[2, 2])
        pts = []
        while len(pts) < per_plane:
            x = np.array([rng.uniform(edges[p], edges[p + 1]), rng.uniform(20, HEIGHT - 20)])
            y = H @ np.array([x[0], x[1], 1.0])
            y = y[:2] / y[2]
            yb = np.linalg.solve(G, np.array([y[0], y[1], 1.0]))[:2]  # in the unturned image
            if 0 <= yb[0] < WIDTH and 0 <= yb[1] < HEIGHT:
                pts.append((x, y))
        a = np.array(pts)
        x1s.append(a[:, 0])
        x2s.append(a[:, 1])
        labels.append(np.full(per_plane, p))
    n_in = n_planes * per_plane
    n_out = int(round(n_in * outlier_ratio / (1 - outlier_ratio)))
    o1 = rng.uniform([0, 0], [WIDTH, HEIGHT], (n_out, 2))
    o2 = rng.uniform([0, 0], [WIDTH, HEIGHT], (n_out, 2))
    o2 = o2 @ G[:2, :2].T + G[:2, 2]
    x1 = np.concatenate(x1s + [o1]) + rng.normal(0, noise, (n_in + n_out, 2))
    x2 = np.concatenate(x2s + [o2]) + rng.normal(0, noise, (n_in + n_out, 2))
    plane = np.concatenate(labels + [np.full(n_out, -1)])
    order = rng.permutation(len(x1))
    return PlaneScene(x1[order], x2[order], plane[order], np.stack(Hs))


def assert_same_mop_runs(method: str, scoring_a, scoring_b, *, scene_seed: int,
                         outlier_ratio: float) -> None:
    """Two scorings of one MOP problem (a planted-plane scene) take the same search: the same
    homographies, round inliers and loop counters, with at least 3 planes found."""
    from colmap_miho.filtering.config import FilterConfig
    from colmap_miho.filtering.miho import build_problem
    from colmap_miho.filtering.mop import run_mop

    sc = make_scene(np.random.default_rng(scene_seed), outlier_ratio=outlier_ratio)
    cfg = FilterConfig(method=method)
    problem = build_problem(sc.x1, sc.x2, miho=cfg.is_miho, full_match=True)
    a = run_mop(problem, cfg, np.random.default_rng(0), scoring=scoring_a)
    b = run_mop(problem, cfg, np.random.default_rng(0), scoring=scoring_b)
    assert len(a.hyps) >= 3
    np.testing.assert_array_equal(a.hyps.H, b.hyps.H)
    np.testing.assert_array_equal(a.round_inliers, b.round_inliers)
    assert a.stats == b.stats
