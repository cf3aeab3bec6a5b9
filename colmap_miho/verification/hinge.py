"""A hinged global estimate: find it, and let each pair's own coverage decide which side is right
(pure numpy; why a hinge arises: ``docs/how-it-works.md``, "A hinged estimate").

Detect (:func:`find_hinges`, :func:`confirm_hinge`: modes of the world-frame residuals
``D_ij = R_j^T R_ij R_i``), measure (:func:`coverage`, :func:`pair_coverage`: missing
correspondences, Zach et al. 2008), group and arbitrate (:func:`split_groups`, :func:`arbitrate`),
and resolve (:func:`resolve_hinge`, the one call of the match check's rounds).
Poses are ``cam_from_world`` ``(R (3, 3), t (3,))``; ``rays`` normalised image coordinates.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..geometry import project_to_so3, rotation_angle_deg
from ..types import Pair, Pose
from .config import MatchCheckConfig
from .estimator import Est, Estimator


def world_residuals(poses: Mapping[int, Pose], pair_rotations: Mapping[Pair, np.ndarray]) -> dict[Pair, np.ndarray]:
    """``D_ij = R_j^T R_ij R_i`` of every pair of two posed images: the identity where the pair's
    own rotation agrees with the estimate; ``G_B^T G_A`` for a correct pair from a group turned
    by ``G_A`` to one turned by ``G_B``."""
    return {(i, j): poses[j][0].T @ R @ poses[i][0] for (i, j), R in pair_rotations.items()
            if i in poses and j in poses}


@dataclass(frozen=True, kw_only=True)
class Hinge:
    """A coherent disagreement of the pairs' own rotations with the estimate.

    Attributes:
        turn: ``(3, 3)`` world rotation ``M`` (the mode of the residuals, oriented from end A to
            end B): turning the B side's cameras by it (``R_j M``) makes the mode's pairs agree.
        angle_deg: the angle of ``turn``.
        ends_a / ends_b: the images of the mode's pairs on each side.
        mode_pairs: the pairs whose residuals form the mode (the other hypothesis' evidence).
        agreeing: the pairs that agree with the estimate (its evidence, within and across).
    """

    turn: np.ndarray
    angle_deg: float
    ends_a: frozenset[int]
    ends_b: frozenset[int]
    mode_pairs: tuple[Pair, ...]
    agreeing: tuple[Pair, ...]


def find_hinges(poses: Mapping[int, Pose], pair_rotations: Mapping[Pair, np.ndarray], *, tolerance_deg: float,
                min_pairs: int, min_side_images: int) -> Iterator[Hinge]:
    """The coherent disagreements of the pairs' own rotations with the estimate, strongest
    first (each is a candidate: :func:`confirm_hinge` tests it).

    A pair disagrees when its residual :func:`world_residuals` is more than ``tolerance_deg``
    from the identity (the trust test's bound). Each disagreeing pair's residual, in both
    orientations, is a candidate mode; its support is the disagreeing pairs within
    ``tolerance_deg`` of it in either orientation (a pair ``(i, j)`` near ``M`` puts i on end
    A and j on end B, near ``M^T`` the other way). Candidates are taken by their support, most
    first, each set of pairs once (a pair that would put an image at both ends is left out:
    :func:`_one_side_each`); one is a hinge when at least ``min_pairs`` pairs support it and
    each end holds at least ``min_side_images`` images.
    """
    residuals = world_residuals(poses, pair_rotations)
    eye = np.eye(3)
    off = {p: D for p, D in residuals.items() if rotation_angle_deg(D, eye) > tolerance_deg}
    if len(off) < min_pairs:
        return
    keys = sorted(off)
    stack = np.stack([off[p] for p in keys])  # (P, 3, 3)
    lim = np.cos(np.deg2rad(tolerance_deg))
    candidates: list[list[tuple[Pair, bool]]] = []
    for p in keys:
        for C in (off[p], off[p].T):
            # the cosine of the angle between C and each D as it is / flipped (D^T): (trace - 1) / 2
            same = (np.einsum("kab,ab->k", stack, C) - 1.0) / 2.0 >= lim
            flip = ((np.einsum("kba,ab->k", stack, C) - 1.0) / 2.0 >= lim) & ~same
            candidates.append([(keys[k], False) for k in np.flatnonzero(same)]
                              + [(keys[k], True) for k in np.flatnonzero(flip)])
    agreeing = tuple(sorted(p for p in residuals if p not in off))
    tried: set[frozenset[Pair]] = set()
    for k in sorted(range(len(candidates)), key=lambda k: (-len(candidates[k]), k)):
        support = candidates[k]
        if len(support) < min_pairs:
            return
        pairs = frozenset(q for q, _ in support)
        if pairs in tried:
            continue
        tried.add(pairs)
        support = _one_side_each(support)
        pairs = frozenset(q for q, _ in support)
        if len(support) < min_pairs:
            continue
        ends_a = {q[1] if f else q[0] for q, f in support}
        ends_b = {q[0] if f else q[1] for q, f in support}
        if len(ends_a) < min_side_images or len(ends_b) < min_side_images:
            continue
        M = project_to_so3(np.sum([off[q].T if f else off[q] for q, f in support], axis=0))
        yield Hinge(turn=M, angle_deg=rotation_angle_deg(M, eye), ends_a=frozenset(ends_a), ends_b=frozenset(ends_b),
                    mode_pairs=tuple(sorted(pairs)), agreeing=agreeing)


def _one_side_each(support: list[tuple[Pair, bool]]) -> list[tuple[Pair, bool]]:
    """The supporting pairs that keep each image on one end: an image named at both ends
    (a wrong pair that happens to fall in the mode, flipped) goes to the end most of its pairs
    put it at (ties: end A), and the pairs that disagree are left out."""
    votes: dict[int, int] = {}
    for (i, j), f in support:
        a, b = (j, i) if f else (i, j)
        votes[a] = votes.get(a, 0) + 1
        votes[b] = votes.get(b, 0) - 1
    return [((i, j), f) for (i, j), f in support
            if votes[j if f else i] >= 0 and votes[i if f else j] < 0]


def confirm_hinge(hinge: Hinge, poses: Mapping[int, Pose], placed: Callable[[int, int], Pose | None], *,
                  tolerance_deg: float, min_pairs: int, min_side_images: int) -> Hinge | None:
    """The hinge with only the mode's pairs whose disagreement holds when the pair's relative
    pose is measured from 3D points, or None when too few of them hold.

    A pair's own relative rotation comes from its essential matrix, which planar scenes make
    ambiguous: pairs of a courtyard whose matches are right can share one wrong rotation and
    form a mode. Placing the second image from the first image's 3D points through the pair's
    matches (``placed(i, j)``: j's ``cam_from_world``, or None) has no such ambiguity; a pair
    of a real hinge disagrees with the estimate by the mode there too (``R_j^T R_j'`` within
    ``tolerance_deg`` of it, oriented as the pair is)."""
    eye = np.eye(3)
    kept: list[tuple[Pair, np.ndarray]] = []
    for p in hinge.mode_pairs:
        i, j = p
        M = hinge.turn.T if i in hinge.ends_b else hinge.turn  # the mode as pair (i, j) sees it
        pose = placed(i, j)
        if pose is not None:
            D = poses[j][0].T @ pose[0]
        else:
            back = placed(j, i)
            if back is None:
                continue
            D = back[0].T @ poses[i][0]
        if rotation_angle_deg(D, M) <= tolerance_deg and rotation_angle_deg(D, eye) > tolerance_deg:
            kept.append((p, D if i not in hinge.ends_b else D.T))
    ends_a = {q[1] if q[0] in hinge.ends_b else q[0] for q, _ in kept}
    ends_b = {q[0] if q[0] in hinge.ends_b else q[1] for q, _ in kept}
    if len(kept) < min_pairs or len(ends_a) < min_side_images or len(ends_b) < min_side_images:
        return None
    M = project_to_so3(np.sum([D for _, D in kept], axis=0))
    return Hinge(turn=M, angle_deg=rotation_angle_deg(M, eye), ends_a=frozenset(ends_a), ends_b=frozenset(ends_b),
                 mode_pairs=tuple(sorted(q for q, _ in kept)), agreeing=hinge.agreeing)


@dataclass(frozen=True, kw_only=True)
class Groups:
    """The two groups a hinge implies (:func:`split_groups`).

    Attributes:
        side_a / side_b: the images joined to each end of the mode.
        across: the pairs that agree with the estimate between the two groups (its evidence
            across the hinge).
    """

    side_a: frozenset[int]
    side_b: frozenset[int]
    across: tuple[Pair, ...]


def split_groups(hinge: Hinge, strength: Callable[[Pair], float]) -> Groups:
    """The two groups of a hinge: the images joined to each of its ends by their strongest
    pairs that agree with the estimate.

    The pairs are taken strongest first (each pair's own evidence, :func:`pair_coverage`); a
    pair joins its images unless that would join the two ends (a maximum spanning forest with
    the two ends as its roots). So every image goes with the end it reaches through its
    strongest links, whatever their number: the wrong pairs that built a hinge agree with the
    estimate and can outnumber the pairs inside a group (a cut by counts would run through a
    group), but by their own evidence they are the weak ones. Images that reach neither end
    stay out of both groups."""
    parent: dict[int, int] = {}

    def root(k: int) -> int:
        parent.setdefault(k, k)
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    a0, b0 = min(hinge.ends_a), min(hinge.ends_b)
    for k in hinge.ends_a:
        parent[root(k)] = root(a0)
    for k in hinge.ends_b:
        parent[root(k)] = root(b0)
    weight = {p: strength(p) for p in hinge.agreeing}
    for p in sorted(hinge.agreeing, key=lambda p: (-weight[p], p)):
        ri, rj = root(p[0]), root(p[1])
        if ri == rj or {ri, rj} == {root(a0), root(b0)}:
            continue
        if rj in (root(a0), root(b0)):  # keep the ends' roots as roots
            ri, rj = rj, ri
        parent[rj] = ri
    side_a = frozenset(k for k in parent if root(k) == root(a0))
    side_b = frozenset(k for k in parent if root(k) == root(b0))
    across = tuple(p for p in hinge.agreeing if (p[0] in side_a and p[1] in side_b)
                   or (p[0] in side_b and p[1] in side_a))
    return Groups(side_a=side_a, side_b=side_b, across=across)


def coverage(points: np.ndarray, matched: np.ndarray, pose_j: Pose, rays_j: np.ndarray, focal_j: float,
             radius_px: float) -> tuple[int, int]:
    """Missing correspondences of one pair, one direction: of image i's 3D points that image j,
    placed by the pair's own matches, sees, how many the pair matches where they project.

    Args:
        points: ``(K, 3)`` world points image i observes (each determined without image j:
            its track holds two images other than j).
        pose_j: ``cam_from_world`` of image j placed from i's points through the pair's matches
            alone (so right for a correct pair whether or not the estimate is hinged, and the
            repeated element's pose for a wrong pair).
        rays_j: ``(N, 2)`` normalised coordinates of j's keypoints.
        focal_j: j's focal length (pixels).
        matched: ``(K,)`` int, for each point, the keypoint of j the pair matches to the
            keypoint of i observing it (-1: none).
        radius_px: a match counts when j's keypoint is at most this far from the projection.

    Returns:
        (expected, found): i's points in front of j and inside the box of j's keypoints, and of
        those the ones the pair matches within ``radius_px`` of where they project.
    """
    if len(points) == 0 or len(rays_j) == 0:
        return 0, 0
    R, t = pose_j
    Z = points @ R.T + t
    front = Z[:, 2] > 1e-9
    proj = np.full((len(Z), 2), np.inf)
    proj[front] = Z[front, :2] / Z[front, 2:3]
    lo, hi = rays_j.min(axis=0), rays_j.max(axis=0)
    inside = front & np.all((proj >= lo) & (proj <= hi), axis=1)
    has = inside & (matched >= 0)
    near = np.linalg.norm(rays_j[matched[has]] - proj[has], axis=1) * focal_j <= radius_px
    return int(inside.sum()), int(near.sum())


class PointsEstimate(Protocol):
    """What the coverage reads of a global estimate (attributes of
    :class:`colmap_miho.sfm.global_estimate.GlobalEstimate`, described there)."""

    @property
    def rays(self) -> Mapping[int, np.ndarray]: ...
    @property
    def focal(self) -> Mapping[int, float]: ...
    @property
    def observations(self) -> Mapping[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]: ...


#: ``place(i, j, matches)``: image j's ``cam_from_world`` from image i's points through the
#: pair's ``matches`` (``(M, 2)``, column 0 into i) alone, or None.
PlacePair = Callable[[int, int, np.ndarray], "Pose | None"]


def pair_coverage(est: PointsEstimate, place: PlacePair, pair: Pair, matches: np.ndarray,
                  radius_px: float, min_hits: int) -> float:
    """The share of the points each image of ``pair`` sees that the pair's own pose puts in
    the other image and that the pair matches there (:func:`coverage`, both directions pooled).

    A direction whose matches hit fewer than ``min_hits`` of the first image's points says
    nothing (too few to place the other image); one with enough whose matches still do not
    place the other image found none of what it should see. NaN when no direction says
    anything."""
    i, j = pair
    m = np.asarray(matches, np.int64)
    expected = found = 0
    for a, b, mm in ((i, j, m), (j, i, m[:, ::-1])):
        if a not in est.observations or b not in est.rays:
            continue
        kp, xyz, pid, length = est.observations[a]
        if np.isin(mm[:, 0], kp).sum() < min_hits:
            continue
        seen_by_b = np.isin(pid, est.observations[b][2]) if b in est.observations else np.zeros(len(pid), bool)
        own = length - seen_by_b >= 2  # the point's track holds two images other than b
        pose = place(a, b, mm)
        if pose is None:  # the pair's matches do not place the other image: nothing found
            expected += int(own.sum())
            continue
        look = np.full(len(est.rays[a]), -1, np.int64)
        look[mm[:, 0]] = mm[:, 1]
        e, f = coverage(xyz[own], look[kp[own]], pose, est.rays[b], est.focal[b], radius_px)
        expected, found = expected + e, found + f
    return found / expected if expected else float("nan")


def arbitrate(estimate_scores: list[float], mode_scores: list[float]) -> str:
    """Which set of cross pairs the coverage evidence supports: "estimate", "mode", or
    "undecided". A side wins when its pairs' scores and the other side's do not overlap in
    their middle halves (the winner's lower quartile above the loser's upper quartile); an
    empty side loses to a non-empty one. Scores that say nothing (NaN) are left out."""
    estimate_scores = [x for x in estimate_scores if np.isfinite(x)]
    mode_scores = [x for x in mode_scores if np.isfinite(x)]
    if not estimate_scores and not mode_scores:
        return "undecided"
    if not mode_scores:
        return "estimate"
    if not estimate_scores:
        return "mode"
    e_lo, e_hi = np.percentile(estimate_scores, [25, 75])
    m_lo, m_hi = np.percentile(mode_scores, [25, 75])
    if m_lo > e_hi:
        return "mode"
    if e_lo > m_hi:
        return "estimate"
    return "undecided"


@dataclass(frozen=True, kw_only=True)
class HingeVerdict:
    """A hinge found in one round's estimate and the coverage evidence's verdict on it."""

    round: int
    hinge: Hinge
    groups: Groups
    mode_coverage: dict[Pair, float]
    estimate_coverage: dict[Pair, float]
    verdict: str
    action: str = ""
    unjudged: frozenset[Pair] = frozenset()


class PairCoverage:
    """Each pair's own evidence under one estimate, measured once: the second image placed from the
    first's points by the pair's matches alone, and the pair's coverage."""

    def __init__(self, estimator: Estimator[Est], est: Est, matches: Mapping[Pair, np.ndarray],
                 radius_px: float, min_hits: int) -> None:
        self.estimator, self.est, self.matches, self.radius = estimator, est, matches, radius_px
        self.min_hits = min_hits
        self.known: dict[Pair, float] = {}
        self.poses: dict[tuple[int, int], Pose | None] = {}

    def _pair_matches(self, i: int, j: int) -> np.ndarray | None:
        if (i, j) in self.matches:
            return np.asarray(self.matches[(i, j)], np.int64)
        if (j, i) in self.matches:
            return np.asarray(self.matches[(j, i)], np.int64)[:, ::-1]
        return None

    def _place(self, i: int, j: int, m: np.ndarray) -> Pose | None:
        if (i, j) not in self.poses:
            self.poses[(i, j)] = self.estimator.place(self.est, j, {(i, j): m}, frozenset({i}),
                                                      min_inliers=self.min_hits)
        return self.poses[(i, j)]

    def placed(self, i: int, j: int) -> Pose | None:
        """Image j's ``cam_from_world`` placed from image i's points by their pair's matches."""
        m = self._pair_matches(i, j)
        return None if m is None else self._place(i, j, m)

    def __call__(self, pair: Pair) -> float:
        if pair not in self.known:
            m = self.matches.get(pair)
            self.known[pair] = (float("nan") if m is None else
                                pair_coverage(self.est, self._place, pair, m, self.radius, self.min_hits))
        return self.known[pair]


def weigh_hinge(coverage: PairCoverage, hinge: Hinge, round_: int) -> HingeVerdict:
    """The estimate's cross pairs against the mode's, each measured by its own coverage."""
    theirs = {p: coverage(p) for p in hinge.mode_pairs}
    groups = split_groups(hinge, lambda p: np.nan_to_num(coverage(p), nan=0.0))
    ours = {p: coverage(p) for p in groups.across}
    verdict = arbitrate(list(ours.values()), list(theirs.values()))
    return HingeVerdict(round=round_, hinge=hinge, groups=groups, mode_coverage=theirs, estimate_coverage=ours,
                        verdict=verdict)


def _weaker_than_the_mode(v: HingeVerdict) -> set[Pair]:
    """The estimate's cross pairs covered worse than the lower quartile of the mode's informative pairs."""
    theirs = [x for x in v.mode_coverage.values() if np.isfinite(x)] or [0.0]
    bar = float(np.percentile(theirs, 25))
    return {p for p, c in v.estimate_coverage.items() if not c >= bar}


def cross_pairs(pairs, groups: Groups) -> frozenset[Pair]:
    """The pairs with one image in each group."""
    a, b = groups.side_a, groups.side_b
    return frozenset(p for p in pairs if (p[0] in a and p[1] in b) or (p[0] in b and p[1] in a))


def resolve_hinge(estimator: Estimator[Est], est: Est, matches: Mapping[Pair, np.ndarray], cfg: MatchCheckConfig,
                  round_: int) -> tuple[Est, list[HingeVerdict], frozenset[Pair]]:
    """Look for a hinge in ``est`` and resolve it.

    Evidence for the estimate keeps it; for the mode, the estimate is made again without its cross
    pairs; undecided, the pairs between the groups are left unjudged (no correct match is removed on
    a guess). Returns (estimate to judge against, hinges found, pairs left unjudged)."""
    found: list[HingeVerdict] = []
    if not cfg.look_for_hinges:
        return est, found, frozenset()
    for attempt in range(2):  # the estimate, and at most one made again
        coverage = PairCoverage(estimator, est, matches, cfg.max_threshold_px, cfg.min_pair_matches)
        tol, n, sides = cfg.max_rotation_deg, cfg.hinge_min_pairs, cfg.hinge_min_side_images
        confirmed = (confirm_hinge(h, est.poses, coverage.placed, tolerance_deg=tol, min_pairs=n, min_side_images=sides)
                     for h in find_hinges(est.poses, est.pair_rotations, tolerance_deg=tol, min_pairs=n,
                                          min_side_images=sides))
        hinge = next((h for h in confirmed if h is not None), None)
        if hinge is None:
            break
        v = weigh_hinge(coverage, hinge, round_)
        if v.verdict == "estimate":
            found.append(dataclasses.replace(v, action="kept"))
            break
        drop = _weaker_than_the_mode(v)
        if v.verdict == "mode" and attempt == 0 and drop:
            again = estimator.estimate({p: m for p, m in matches.items() if p not in drop})
            if len(again.poses) >= cfg.min_trusted_images:
                found.append(dataclasses.replace(v, action="estimated again"))
                est = again
                continue
        unjudged = cross_pairs(matches, v.groups)
        found.append(dataclasses.replace(v, action="judged less", unjudged=unjudged))
        return est, found, unjudged
    return est, found, frozenset()
