"""Match check core: judge every match against a global estimate of the cameras (pure numpy).

A facade with repeated windows gives matches shifted by one period that agree with a local
homography and with the pair's own fundamental matrix (fitted to both populations): no check of
the pair alone can see them. A global estimate of all cameras (rotations averaged over the
whole pair graph, positions from all tracks) is not bent by one pair's wrong matches, so the
distance of a match to its epipolar line under that estimate exposes them.

The estimate is trusted image by image (:func:`trusted_images`): an image whose estimated pose
disagrees with its pairs' own relative rotations is left out (its matches are kept unjudged),
and when too few images hold, the estimate is not used at all (:func:`check_matches`: nothing is
removed). A group of images placed wrong together agrees with its own pairs and passes that
test; its correct pairs to the rest of the scene then fail, and removing them would cut it off.
So removals never split the pair graph (:func:`cut_off_images`): images they would cut off are
not trusted either. The threshold follows the estimate's own residuals (:func:`robust_scale`).

Conventions: poses are ``cam_from_world`` ``(R (3, 3), t (3,))`` (``X_cam = R X + t``);
``rays`` are a camera's normalised image coordinates ``(N, 2)`` (undistorted, ``K^-1 x``) of an
image's keypoints; ``focal`` is the camera's mean focal length in pixels, which turns a
distance in normalised coordinates into pixels.

Pure: arrays in, a small result out; no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..enums import MatchCheckMode
from .config import MatchCheckConfig

#: An image pair (image_id1, image_id2) with image_id1 < image_id2.
Pair = tuple[int, int]
#: A ``cam_from_world`` pose: rotation (3, 3), translation (3,).
Pose = tuple[np.ndarray, np.ndarray]

def skew(t: np.ndarray) -> np.ndarray:
    """``(3, 3)`` cross-product matrix of ``t`` ``(3,)``."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def relative_pose(pose1: Pose, pose2: Pose) -> Pose:
    """``cam2_from_cam1`` of two ``cam_from_world`` poses."""
    R = pose2[0] @ pose1[0].T
    return R, pose2[1] - R @ pose1[1]


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (degrees) of the rotation ``Ra^T Rb`` between two ``(3, 3)`` rotations."""
    c = (float(np.trace(Ra.T @ Rb)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def essential(rel: Pose) -> np.ndarray:
    """``E_2from1`` ``(3, 3)`` of a relative pose (translation normalised; zero baseline gives
    a zero matrix, whose distances are then undefined and come out as ``inf``)."""
    R, t = rel
    n = float(np.linalg.norm(t))
    return skew(t / n) @ R if n > 0 else np.zeros((3, 3))


def symmetric_epipolar_distance(E: np.ndarray, y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distances ``(d(y2, E y1) + d(y1, E^T y2)) / 2`` of
    normalised correspondences ``y1, y2`` ``(M, 2)``, in normalised units: ``(M,)``; ``inf``
    where a line is undefined."""
    h1 = np.column_stack([y1, np.ones(len(y1))])
    h2 = np.column_stack([y2, np.ones(len(y2))])
    l2 = h1 @ E.T  # lines in image 2
    l1 = h2 @ E  # lines in image 1
    num = np.abs(np.sum(h2 * l2, axis=1))
    n2 = np.hypot(l2[:, 0], l2[:, 1])
    n1 = np.hypot(l1[:, 0], l1[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 0.5 * (num / n2 + num / n1)
    d[~np.isfinite(d)] = np.inf
    return d


def robust_scale(distances: np.ndarray) -> float:
    """Mean ``b`` of the distances of correct matches modelled as exponential (a folded
    Laplace residual: keypoint errors have heavier tails than a normal's), from their median:
    ``b = median / ln 2``. The wrong matches' distances lie far out and only push the median
    up a little (with a share ``w`` of them, it is the ``0.5 / (1 - w)`` quantile of the
    correct ones), so the threshold errs towards keeping. 0 for no distances."""
    d = np.asarray(distances, np.float64)
    d = d[np.isfinite(d)]
    return float(np.median(d)) / np.log(2.0) if d.size else 0.0


def threshold_px(scale: float, false_reject: float, lo: float, hi: float) -> float:
    """The distance an exponential of mean ``scale`` exceeds with probability
    ``false_reject`` (``scale * ln(1 / false_reject)``), clamped to ``[lo, hi]``."""
    return float(np.clip(scale * np.log(1.0 / false_reject), lo, hi))


def trusted_images(poses: Mapping[int, Pose], pair_rotations: Mapping[Pair, np.ndarray],
                   max_rotation_deg: float, min_agreeing_pairs: int
                   ) -> tuple[set[int], dict[int, int], dict[int, int]]:
    """The images whose estimated pose agrees with their pairs' own relative rotations.

    A pair's own rotation (from its matches alone) is right for a correct pair and arbitrary
    for a wrong one (repeated or symmetric structure: on real scenes many pairs are wrong, so
    a median over an image's pairs is not robust). A wrong pose agrees with no correct pair,
    and a wrong pair agrees with the estimate only by chance, so the test counts agreements:
    an image is trusted when at least ``min_agreeing_pairs`` of its pairs agree within
    ``max_rotation_deg``.

    Args:
        poses: image id -> estimated ``cam_from_world``.
        pair_rotations: pair -> the pair's own ``R_2from1`` (from its matches alone).
        max_rotation_deg: a pair agrees when the angle between its rotation and the
            estimate's is at most this.
        min_agreeing_pairs: agreeing pairs an image needs.

    Returns:
        (trusted image ids, image id -> its agreeing pairs, image id -> its pairs with a
        rotation), the counts for every registered image with at least one pair rotation.
    """
    agree: dict[int, int] = {}
    total: dict[int, int] = {}
    for (i, j), R in pair_rotations.items():
        if i in poses and j in poses:
            ok = rotation_angle_deg(relative_pose(poses[i], poses[j])[0], R) <= max_rotation_deg
            for k in (i, j):
                total[k] = total.get(k, 0) + 1
                agree[k] = agree.get(k, 0) + int(ok)
    return {k for k, n in agree.items() if n >= min_agreeing_pairs}, agree, total


def _largest_component(edges: list[Pair], nodes: list[int]) -> set[int]:
    """The largest connected component of the graph (``nodes``, ``edges``); of equal ones, the
    one holding the smallest node."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not nodes:
        return set()
    index = {n: k for k, n in enumerate(nodes)}
    rows = np.asarray([index[i] for i, _ in edges], np.int64)
    cols = np.asarray([index[j] for _, j in edges], np.int64)
    graph = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(len(nodes), len(nodes)))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    best = int(labels[int(np.flatnonzero(sizes[labels] == sizes.max())[0])])  # nodes sorted: smallest first
    return {n for n, lab in zip(nodes, labels, strict=True) if lab == best}


def cut_off_images(matches: Mapping[Pair, np.ndarray], failed: Mapping[Pair, np.ndarray],
                   wrong: set[Pair] | tuple[Pair, ...], min_pair_matches: int) -> set[int]:
    """The images that removing the failed matches and the wrong pairs would cut off the main
    part of the pair graph.

    A pair links its images when it holds at least ``min_pair_matches`` matches (before: all
    of them; after: those that did not fail, none for a wrong pair). Returns the images of the
    largest component before that are outside the largest component after.
    """
    nodes = sorted({i for p in matches for i in p})
    before = [p for p, m in matches.items() if len(m) >= min_pair_matches]
    after = [p for p, m in matches.items() if p not in wrong
             and len(m) - (int(np.count_nonzero(failed[p])) if p in failed else 0) >= min_pair_matches]
    return _largest_component(before, nodes) - _largest_component(after, nodes)


@dataclass(frozen=True, kw_only=True)
class MatchCheckResult:
    """What the match check found.

    Attributes:
        used: the estimate was trusted (enough images) and the matches were judged.
        reason: why it was not used ("" when used).
        registered: images the estimate placed.
        trusted: images whose pose the check trusted (their pairs were judged).
        cut_off: images that agreed with their pairs but that the removals would have cut off
            the rest of the pair graph (placed wrong as a group): not trusted.
        agreeing_pairs / rotation_pairs: image id -> its pairs whose own relative rotation
            agrees with the estimate's / its pairs with an own rotation.
        scale_px: mean of the judged matches' distances under the exponential model
            (:func:`robust_scale`, pixels).
        threshold_px: the distance above which a match failed.
        failed: pair -> bool ``(M,)``: the pair's matches that failed (only judged pairs).
        wrong_pairs: judged pairs most of whose matches failed (removed as a whole).
        pair_fail_share: judged pair -> its share of failing matches.
        matches_judged / matches_failed: over the judged pairs (wrong pairs included).
    """

    used: bool
    reason: str = ""
    registered: frozenset[int] = frozenset()
    trusted: frozenset[int] = frozenset()
    cut_off: frozenset[int] = frozenset()
    agreeing_pairs: dict[int, int] = field(default_factory=dict)
    rotation_pairs: dict[int, int] = field(default_factory=dict)
    scale_px: float = 0.0
    threshold_px: float = 0.0
    failed: dict[Pair, np.ndarray] = field(default_factory=dict)
    wrong_pairs: tuple[Pair, ...] = ()
    pair_fail_share: dict[Pair, float] = field(default_factory=dict)
    matches_judged: int = 0
    matches_failed: int = 0


def check_matches(matches: Mapping[Pair, np.ndarray], rays: Mapping[int, np.ndarray],
                  focal: Mapping[int, float], poses: Mapping[int, Pose],
                  pair_rotations: Mapping[Pair, np.ndarray], cfg: MatchCheckConfig,
                  threshold: float | None = None) -> MatchCheckResult:
    """Judge the matches of every pair of two trusted images against the estimate.

    Args:
        matches: pair -> int ``(M, 2)`` keypoint indices (image_id1, image_id2).
        rays: image id -> ``(N, 2)`` normalised coordinates of its keypoints (registered
            images only).
        focal: image id -> focal length in pixels (registered images).
        poses: image id -> estimated ``cam_from_world`` (the registered images).
        pair_rotations: pair -> its own relative rotation ``R_2from1`` (pairs with at least
            ``cfg.min_pair_matches`` matches whose own pose could be estimated).
        cfg: the thresholds.
        threshold: pixels; use this threshold instead of the one from these matches'
            distances (a later round, judging the survivors of the first: their distances are
            truncated, and a scale taken from them would shrink round after round).

    Returns:
        A :class:`MatchCheckResult`; ``used`` False (nothing failed) when fewer than
        ``cfg.min_trusted_images`` images, or less than ``cfg.min_trusted_share`` of the
        registered ones, are trusted.
    """
    registered = frozenset(int(k) for k in poses)
    if len(registered) < cfg.min_trusted_images:
        return MatchCheckResult(used=False, registered=registered,
                                reason=f"the global estimate placed {len(registered)} images "
                                       f"(at least {cfg.min_trusted_images} needed)")
    trusted, agree, total = trusted_images(poses, pair_rotations, cfg.max_rotation_deg, cfg.min_agreeing_pairs)
    needed = max(cfg.min_trusted_images, int(np.ceil(cfg.min_trusted_share * len(registered))))
    if len(trusted) < needed:
        return MatchCheckResult(
            used=False, registered=registered, trusted=frozenset(trusted), agreeing_pairs=agree, rotation_pairs=total,
            reason=f"{len(trusted)} of the {len(registered)} placed images agree with their pairs' own "
                   f"relative rotations (at least {cfg.min_agreeing_pairs} pairs within {cfg.max_rotation_deg:g} deg; "
                   f"{needed} images needed)")
    dist_all: dict[Pair, np.ndarray] = {}  # every pair of two trusted images, once
    for (i, j), m in matches.items():
        if i in trusted and j in trusted and len(m):
            m = np.asarray(m, np.int64)
            E = essential(relative_pose(poses[i], poses[j]))
            d = symmetric_epipolar_distance(E, rays[i][m[:, 0]], rays[j][m[:, 1]])
            dist_all[(i, j)] = d * float(np.sqrt(focal[i] * focal[j]))
    cut: set[int] = set()
    given = threshold
    while True:  # judge; drop from the trusted images any the removals would cut off; again
        dist = {p: d for p, d in dist_all.items() if p[0] in trusted and p[1] in trusted}
        all_d = np.concatenate(list(dist.values())) if dist else np.zeros(0)
        scale = robust_scale(all_d)
        threshold = given if given is not None else threshold_px(scale, cfg.false_reject, cfg.min_threshold_px,
                                                                 cfg.max_threshold_px)
        failed = {p: d > threshold for p, d in dist.items()}
        share = {p: float(f.mean()) for p, f in failed.items()}
        wrong = tuple(sorted(p for p, f in failed.items()
                             if len(f) >= cfg.min_pair_matches and share[p] > cfg.max_pair_fail_share))
        lost = cut_off_images(matches, failed, wrong, cfg.min_pair_matches) & trusted
        if not lost:
            break
        cut |= lost
        trusted -= lost
        if len(trusted) < needed:
            return MatchCheckResult(
                used=False, registered=registered, trusted=frozenset(trusted), cut_off=frozenset(cut),
                agreeing_pairs=agree, rotation_pairs=total,
                reason=f"removing the matches that fail the global estimate would cut {len(cut)} images off the "
                       f"rest of the pair graph; {len(trusted)} trusted images left ({needed} needed)")
    return MatchCheckResult(
        used=True, registered=registered, trusted=frozenset(trusted), cut_off=frozenset(cut), agreeing_pairs=agree,
        rotation_pairs=total, scale_px=scale, threshold_px=threshold, failed=failed, wrong_pairs=wrong,
        pair_fail_share=share, matches_judged=int(all_d.size),
        matches_failed=int(sum(int(f.sum()) for f in failed.values())))


def removes(result: MatchCheckResult, mode: MatchCheckMode) -> bool:
    """The result removes something: used, in "remove" mode."""
    return result.used and mode == MatchCheckMode.REMOVE
