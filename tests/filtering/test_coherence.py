"""Plane coherence check (FilterConfig.coherence): spurious planes of repeated-texture
mismatches are dropped, spatially separate true planes are kept."""

from __future__ import annotations

import numpy as np
from planes import HEIGHT, WIDTH, make_scene

from colmap_miho import filter_matches
from colmap_miho.filtering.coherence import contradicted, incoherent_planes
from colmap_miho.filtering.config import FilterConfig


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.c_[pts, np.ones(len(pts))] @ H.T
    return q[:, :2] / q[:, 2:]


def _repeated_texture_pair(seed: int):
    """One plane filling image 1 (500 matches), 14 mismatches that all land one texture period
    (70 px) right of their true position (a consistent, spurious plane scattered over the
    same area), and 60 random matches."""
    rng = np.random.default_rng(seed)
    H = np.array([[1.05, 0.04, 12.0], [-0.03, 0.98, -8.0], [2e-5, -1e-5, 1.0]])
    x1 = rng.uniform([40, 40], [WIDTH - 120, HEIGHT - 40], (500, 2))
    x2 = _apply(H, x1) + rng.normal(0, 0.5, x1.shape)
    r1 = rng.uniform([40, 40], [WIDTH - 120, HEIGHT - 40], (14, 2))
    r2 = _apply(H, r1) + [70.0, 0.0] + rng.normal(0, 0.5, r1.shape)
    o1 = rng.uniform(0, [WIDTH, HEIGHT], (60, 2))
    o2 = rng.uniform(0, [WIDTH, HEIGHT], (60, 2))
    kind = np.r_[np.zeros(500, int), np.ones(14, int), np.full(60, 2)]
    return np.r_[x1, r1, o1], np.r_[x2, r2, o2], kind


def test_spurious_plane_of_shifted_matches_is_dropped():
    """Without the check MOP+MiHo keeps the shifted matches as a plane of their own; with it
    they go, and the true plane keeps its matches."""
    for seed in range(3):
        p1, p2, kind = _repeated_texture_pair(seed)
        plain = filter_matches(p1, p2, config=FilterConfig(miho_threshold="full"), seed=seed)
        checked = filter_matches(p1, p2, config=FilterConfig(miho_threshold="full", coherence=True),
                                 seed=seed)
        assert plain.inliers[kind == 1].sum() >= 8, "the spurious plane must exist to be dropped"
        assert checked.inliers[kind == 1].sum() == 0
        assert checked.stats["coherence_dropped"] >= 1
        assert checked.inliers[kind == 0].mean() >= plain.inliers[kind == 0].mean() - 0.002
        assert checked.num_homographies == plain.num_homographies - checked.stats["coherence_dropped"]
        assert checked.labels.max() < checked.num_homographies


def test_separate_true_planes_are_kept():
    """Planes in separate image strips (a multi-plane scene) are coherent: nothing dropped."""
    for seed in range(3):
        scene = make_scene(np.random.default_rng(seed), n_planes=3, outlier_ratio=0.3)
        for method in ("mop", "mop_miho"):
            plain = filter_matches(scene.x1, scene.x2, method=method, seed=seed)
            checked = filter_matches(scene.x1, scene.x2, method=method, seed=seed,
                                     config=FilterConfig(coherence=True))
            assert checked.stats["coherence_dropped"] == 0
            np.testing.assert_array_equal(checked.inliers, plain.inliers)
            np.testing.assert_array_equal(checked.labels, plain.labels)


def test_contradicted_needs_both_images():
    """Matches scattered among another plane's matches, and incompatible with it, are
    contradicted when that holds in both images; when they cluster together in image 2 (their
    neighbours there are their own plane's) they are not; compatible with the other plane, they
    are not either."""
    rng = np.random.default_rng(0)
    x1 = rng.uniform(0, 100, (40, 2))
    x2 = x1.copy()
    labels = np.zeros(40, dtype=int)
    labels[:5] = 1
    compat = np.stack([labels == 0, labels == 1])
    assert contradicted(x1, x2, labels, compat)[:5].all()
    assert not contradicted(x1, x2, labels, compat)[5:].any()
    clustered = x2.copy()
    clustered[:5] = 500.0 + rng.uniform(0, 2, (5, 2))  # 4 own-plane neighbours of 8 in image 2
    assert not contradicted(x1, clustered, labels, compat)[:5].any()
    both = compat.copy()
    both[0, :5] = True
    assert not contradicted(x1, x2, labels, both)[:5].any()
    assert not contradicted(x1[:8], x2[:8], labels[:8], compat[:, :8]).any()  # too few matches


def test_incoherent_planes_spare_the_largest():
    """Two interleaved planes that contradict each other: only the smaller one is dropped."""
    rng = np.random.default_rng(1)
    x1 = rng.uniform(0, 100, (60, 2))
    labels = np.r_[np.zeros(40, int), np.ones(20, int)]
    rng.shuffle(labels)
    compat = np.stack([labels == 0, labels == 1])
    assert incoherent_planes(x1, x1, labels, compat).tolist() == [1]
    labels_unkept = np.where(labels == 1, -1, labels)
    assert incoherent_planes(x1, x1, labels_unkept, compat).tolist() == []
