"""A hinged global estimate: the mode of the pairs' disagreements, its confirmation from 3D
points, the groups, each pair's coverage and the arbiter (pure numpy, planted geometry)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.geometry import relative_pose, rotation_angle_deg
from colmap_miho.verification.hinge import (
    Hinge,
    arbitrate,
    confirm_hinge,
    coverage,
    find_hinges,
    split_groups,
    world_residuals,
)

TOL = 5.0
GROUP_A = range(1, 6)
GROUP_B = range(6, 11)


def find_hinge(poses, pair_rotations, **kwargs) -> Hinge | None:
    """The strongest candidate of :func:`find_hinges`, or None."""
    return next(find_hinges(poses, pair_rotations, **kwargs), None)


def _rot(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _arc(n: int = 10) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Cameras 1..n on an arc, looking at the origin from 6 units."""
    poses = {}
    for k in range(n):
        ang = -50 + 100 * k / (n - 1)
        R = _rot([0, 1, 0], ang)
        centre = np.array([6 * np.sin(np.radians(-ang)), 0.0, -6 * np.cos(np.radians(ang))])
        poses[k + 1] = (R, -R @ centre)
    return poses


def _true_rotations(poses, pairs):
    return {p: relative_pose(poses[p[0]], poses[p[1]])[0] for p in pairs}


def _hinged(turn_deg: float = 40.0):
    """The true cameras, and an estimate with group B turned by ``turn_deg`` (right inside each
    group); every pair's own rotation is the true one."""
    poses = _arc()
    G = _rot([0.2, 1, 0.1], turn_deg)
    est = {k: ((R @ G, t) if k in GROUP_B else (R, t)) for k, (R, t) in poses.items()}
    pairs = [(i, j) for i in poses for j in poses if i < j and j - i <= 3]
    return poses, est, _true_rotations(poses, pairs), G


def test_residuals_of_an_agreeing_pair_are_the_identity_and_of_a_cross_pair_the_turn():
    _, est, rot, G = _hinged()
    D = world_residuals(est, rot)
    assert rotation_angle_deg(D[(1, 2)], np.eye(3)) < 1e-6
    assert rotation_angle_deg(D[(4, 6)], G.T) < 1e-6  # G_B^T G_A with G_A = I


@pytest.mark.parametrize("turn", [30.0, 47.0, 60.0])
def test_a_group_turned_together_is_a_hinge_with_its_ends(turn):
    _, est, rot, G = _hinged(turn)
    h = find_hinge(est, rot, tolerance_deg=TOL, min_pairs=3, min_side_images=2)
    assert h is not None
    assert h.angle_deg == pytest.approx(turn, abs=0.5)
    ends = {frozenset(h.ends_a), frozenset(h.ends_b)}
    assert ends == {frozenset({3, 4, 5}), frozenset({6, 7, 8})}  # the images the cross pairs join
    assert set(h.mode_pairs) == {p for p in rot if (p[0] in GROUP_A) != (p[1] in GROUP_A)}
    assert not set(h.agreeing) & set(h.mode_pairs)


def test_disagreements_that_scatter_are_no_hinge():
    poses = _arc()
    pairs = [(i, j) for i in poses for j in poses if i < j]
    rot = _true_rotations(poses, pairs)
    rng = np.random.default_rng(0)
    for p in pairs[::3]:  # wrong pairs with unrelated rotations
        rot[p] = _rot(rng.normal(size=3), rng.uniform(20, 170))
    assert find_hinge(poses, rot, tolerance_deg=TOL, min_pairs=3, min_side_images=2) is None


def test_one_image_turned_alone_is_the_trust_tests_case():
    poses = _arc()
    pairs = [(i, j) for i in poses for j in poses if i < j]
    rot = _true_rotations(poses, pairs)
    est = {**poses, 4: (poses[4][0] @ _rot([0, 1, 0], 30.0), poses[4][1])}
    assert find_hinge(est, rot, tolerance_deg=TOL, min_pairs=3, min_side_images=2) is None
    assert find_hinge(est, rot, tolerance_deg=TOL, min_pairs=3, min_side_images=1) is not None


def test_a_mode_that_3d_points_do_not_confirm_is_dropped():
    """A mode of pairs whose essential matrices share one wrong rotation (a planar courtyard)
    while placing the images from 3D points agrees with the estimate: no hinge. The same mode
    confirmed by the placements stays."""
    poses, est, rot, _ = _hinged()
    h = find_hinge(est, rot, tolerance_deg=TOL, min_pairs=3, min_side_images=2)
    assert h is not None

    def as_estimated(i, j):  # the points place j where the estimate has it
        return est[j]

    def as_true(i, j):  # the points place j where the truth (relative to i) has it
        R_ij, t_ij = relative_pose(poses[i], poses[j])
        R_i, t_i = est[i]
        return R_ij @ R_i, R_ij @ t_i + t_ij

    assert confirm_hinge(h, est, as_estimated, tolerance_deg=TOL, min_pairs=3, min_side_images=2) is None
    kept = confirm_hinge(h, est, as_true, tolerance_deg=TOL, min_pairs=3, min_side_images=2)
    assert kept is not None and set(kept.mode_pairs) == set(h.mode_pairs)
    assert kept.angle_deg == pytest.approx(h.angle_deg, abs=0.1)
    none = confirm_hinge(h, est, lambda i, j: None, tolerance_deg=TOL, min_pairs=3, min_side_images=2)
    assert none is None  # nothing placed: nothing confirms


def test_groups_follow_the_strongest_pairs_whatever_their_number():
    """Many weak pairs across (a hinge's wrong pairs) against fewer strong pairs inside each
    group: each image goes with its strong links; the weak pairs are the ones across."""
    a, b = [1, 2, 3, 4], [5, 6, 7, 8]
    inside = [(1, 2), (2, 3), (3, 4), (5, 6), (6, 7), (7, 8)]
    weak = [(i, j) for i in a for j in b if (i, j) != (4, 5)]  # 15 pairs across, weak
    h = Hinge(turn=np.eye(3), angle_deg=40.0, ends_a=frozenset({1}), ends_b=frozenset({8}),
              mode_pairs=((4, 5),), agreeing=tuple(sorted(inside + weak)))
    g = split_groups(h, lambda p: 0.9 if p in inside else 0.4)
    assert g.side_a == frozenset(a) and g.side_b == frozenset(b)
    assert set(g.across) == set(weak)
    lone = Hinge(turn=np.eye(3), angle_deg=40.0, ends_a=frozenset({1}), ends_b=frozenset({8}),
                 mode_pairs=((4, 5),), agreeing=((1, 2),))
    g = split_groups(lone, lambda p: 1.0)
    assert g.side_a == frozenset({1, 2}) and g.side_b == frozenset({8}) and g.across == ()


def test_arbitrate_compares_the_two_sets():
    strong, weak = [0.8, 0.85, 0.9, 0.82], [0.3, 0.4, 0.35, 0.45, 0.5]
    assert arbitrate(weak, strong) == "mode"
    assert arbitrate(strong, weak) == "estimate"
    assert arbitrate([0.3, 0.9, 0.5, 0.7], [0.4, 0.8, 0.6]) == "undecided"
    assert arbitrate([float("nan"), *weak], strong) == "mode"  # NaN says nothing
    assert arbitrate([], strong) == "mode" and arbitrate(weak, []) == "estimate"
    assert arbitrate([], []) == "undecided"


def test_coverage_counts_what_the_pair_should_see_and_matches_there():
    rng = np.random.default_rng(1)
    points = rng.uniform([-1, -1, 4], [1, 1, 6], (200, 3))
    pose_j = (_rot([0, 1, 0], 10.0), np.array([0.5, 0.0, 0.0]))
    Z = points @ pose_j[0].T + pose_j[1]
    rays = Z[:, :2] / Z[:, 2:3]
    focal = 800.0
    behind = np.array([[0.0, 0.0, -3.0]]) - pose_j[1] @ pose_j[0]  # a point behind camera j
    pts = np.vstack([points, behind @ pose_j[0]])
    matched = np.full(len(pts), -1)
    matched[:120] = np.arange(120)  # matched where they project
    matched[120:150] = np.arange(120, 150)[::-1]  # matched to the wrong keypoints
    e, f = coverage(pts, matched, pose_j, rays, focal, radius_px=4.0)
    assert e == 200  # the point behind j is not expected
    assert 120 <= f <= 121  # a reversed keypoint may land on itself
    assert coverage(pts[:0], matched[:0], pose_j, rays, focal, 4.0) == (0, 0)


def test_a_wrong_pair_in_the_mode_that_names_an_image_at_both_ends_is_left_out():
    """A wrong pair inside group B whose own rotation happens to fall in the mode, flipped, would
    put image 6 at both ends; it is left out and the hinge stays the same."""
    _, est, rot, G = _hinged()
    rot[(6, 9)] = est[9][0] @ G.T @ est[6][0].T  # D_69 = G^T: the cross pairs' residual, 6 at end A
    h = find_hinge(est, rot, tolerance_deg=TOL, min_pairs=3, min_side_images=2)
    assert h is not None and not h.ends_a & h.ends_b
    assert {frozenset(h.ends_a), frozenset(h.ends_b)} == {frozenset({3, 4, 5}), frozenset({6, 7, 8})}
    assert (6, 9) not in h.mode_pairs
