"""Match check core (pure numpy): judge every match against a global estimate of the cameras. Poses
are ``cam_from_world``; ``rays`` ``(N, 2)`` are undistorted normalised keypoints; ``focal`` (pixels)
turns a normalised distance into pixels."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..geometry import essential, relative_pose, rotation_angle_deg, symmetric_epipolar_distance
from ..types import Pair, Pose
from .config import MatchCheckConfig
from .estimator import CameraEstimate, Est, Estimator
from .hinge import HingeVerdict, resolve_hinge
from .restore import restore_matches


@dataclass(frozen=True, kw_only=True)
class MatchCheckDecision:
    """The match check's result: what :func:`judge_in_rounds` decided over all its rounds
    (``failed``: pair -> bool ``(M,)``; ``scale_px`` / ``threshold_px`` from the first used round;
    ``unjudged``: pairs across an undecided hinge; ``restored``: candidate pair -> bool ``(R,)``,
    the filter's removals given back)."""

    used: bool
    reason: str = ""
    rounds: int = 0
    failed: dict[Pair, np.ndarray] = field(default_factory=dict)
    wrong: frozenset[Pair] = frozenset()
    fail_share: dict[Pair, float] = field(default_factory=dict)
    registered: frozenset[int] = frozenset()
    trusted: frozenset[int] = frozenset()
    untrusted: frozenset[int] = frozenset()
    cut_off: frozenset[int] = frozenset()
    judged_pairs: frozenset[Pair] = frozenset()
    scale_px: float = 0.0
    threshold_px: float = 0.0
    seconds: list[dict[str, float]] = field(default_factory=list)
    mapper_steps: list[dict[str, float]] = field(default_factory=list)
    hinges: tuple[HingeVerdict, ...] = ()
    unjudged: frozenset[Pair] = frozenset()
    restored: dict[Pair, np.ndarray] = field(default_factory=dict)


@dataclass(kw_only=True)
class _Rounds:
    """What :func:`judge_in_rounds` carries from one round to the next (``trusted``,
    ``registered``, ``cut_off``: in any round; ``focus``: a later round's images, those not
    trusted yet; ``offered``: candidate pairs a round's estimate has judged)."""

    failed: dict[Pair, np.ndarray]
    wrong: set[Pair] = field(default_factory=set)
    trusted: set[int] = field(default_factory=set)
    registered: set[int] = field(default_factory=set)
    cut_off: set[int] = field(default_factory=set)
    used: bool = False
    reason: str = ""
    scale_px: float = 0.0
    threshold_px: float = 0.0
    rounds: int = 0
    seconds: list[dict[str, float]] = field(default_factory=list)
    mapper_steps: list[dict[str, float]] = field(default_factory=list)
    hinges: list[HingeVerdict] = field(default_factory=list)
    unjudged: set[Pair] = field(default_factory=set)
    focus: set[int] | None = None
    restored: dict[Pair, np.ndarray] = field(default_factory=dict)
    offered: set[Pair] = field(default_factory=set)

    def alive(self, matches: Mapping[Pair, np.ndarray]) -> dict[Pair, np.ndarray]:
        """The rows of each pair still standing, pair -> int ``(K,)``; a later round only around
        its focus."""
        alive = {p: np.flatnonzero(~f) for p, f in self.failed.items() if p not in self.wrong and (~f).any()}
        if self.focus is not None:
            near = images_around(self.focus, alive, LATER_ROUND_RINGS)
            alive = {p: idx for p, idx in alive.items() if p[0] in near and p[1] in near}
        return alive

    def take(self, res: Judgement, alive: Mapping[Pair, np.ndarray]) -> None:
        """A used round's judgement: the first round's scale and threshold kept; a later round
        fails only matches of pairs not trusted on both sides before it."""
        if not self.used:
            self.scale_px, self.threshold_px = res.scale_px, res.threshold_px
        self.used, self.reason = True, ""
        for p, f in res.failed.items():
            if not (p[0] in self.trusted and p[1] in self.trusted):
                self.failed[p][alive[p][f]] = True
        self.trusted |= set(res.trusted)
        self.wrong |= set(res.wrong_pairs)

    def restore(self, candidates: Mapping[Pair, np.ndarray], res: Judgement,
                judged: Mapping[Pair, np.ndarray], est: CameraEstimate) -> None:
        """Offer the candidates of pairs this round trusts on both sides (each pair once)."""
        offer = {p: c for p, c in candidates.items()
                 if p not in self.offered and p not in self.wrong and p[0] in res.trusted and p[1] in res.trusted}
        self.offered |= set(offer)
        kept = {p: m[~res.failed[p]] if p in res.failed else m for p, m in judged.items()
                if p not in res.wrong_pairs}
        self.restored.update(restore_matches(offer, kept, est.rays, est.focal, res.poses, res.trusted,
                                             self.threshold_px))

    def decision(self, matches: Mapping[Pair, np.ndarray]) -> MatchCheckDecision:
        """The decision over all rounds; a wrong pair's matches all fail."""
        judged = frozenset(p for p in matches if p[0] in self.trusted and p[1] in self.trusted
                           and p not in self.unjudged)
        share = {p: float(self.failed[p].mean()) for p in self.wrong}  # before the pair is removed whole
        for p in self.wrong:
            self.failed[p][:] = True
        return MatchCheckDecision(
            used=self.used, reason=self.reason, rounds=self.rounds,
            failed={p: f for p, f in self.failed.items() if f.any() or p in judged}, wrong=frozenset(self.wrong),
            fail_share=share, registered=frozenset(self.registered), trusted=frozenset(self.trusted),
            untrusted=frozenset(self.registered - self.trusted), cut_off=frozenset(self.cut_off),
            judged_pairs=judged, scale_px=self.scale_px, threshold_px=self.threshold_px, seconds=self.seconds,
            mapper_steps=self.mapper_steps, hinges=tuple(self.hinges), unjudged=frozenset(self.unjudged),
            restored={p: r for p, r in self.restored.items() if p not in self.wrong})


def judge_in_rounds(matches: Mapping[Pair, np.ndarray], estimator: Estimator[Est],
                    cfg: MatchCheckConfig, candidates: Mapping[Pair, np.ndarray] | None = None) -> MatchCheckDecision:
    """The match check: up to ``cfg.max_rounds`` estimates, each from the last one's survivors. Later
    rounds estimate only around untrusted images and keep the first threshold (the survivors'
    distances are truncated, so a scale taken from them would shrink round after round).
    ``candidates`` (pair -> ``(R, 2)``, the matches the filter removed) come back where a round's
    estimate and kept matches prove them (:mod:`.restore`)."""
    s = _Rounds(failed={p: np.zeros(len(m), bool) for p, m in matches.items()})
    for _ in range(cfg.max_rounds):
        alive = s.alive(matches)
        current = {p: matches[p][idx] for p, idx in alive.items()}
        est = estimator.estimate(current)
        s.rounds += 1
        part = dict(est.seconds)
        s.mapper_steps.append(dict(est.mapper_steps))
        th = time.perf_counter()
        est, found, skip = resolve_hinge(estimator, est, current, cfg, s.rounds)
        if cfg.look_for_hinges:
            part["hinge"] = time.perf_counter() - th  # the search; a second estimate included
        s.hinges += found
        s.unjudged |= skip
        judged_now = {p: m for p, m in current.items() if p not in s.unjudged}  # left unjudged in any round
        given = s.threshold_px if s.used else None
        t0 = time.perf_counter()
        res = check_matches(judged_now, est.rays, est.focal, est.poses, est.pair_rotations, cfg, threshold=given)
        t1 = time.perf_counter()
        res = place_untrusted(estimator, est, res, judged_now, cfg, given)
        s.seconds.append({**part, "judging": t1 - t0, "placements": time.perf_counter() - t1})
        s.cut_off |= set(res.cut_off)  # the first judgement's and the placements' together
        s.registered |= set(res.registered)
        if not res.used:
            why = res.reason + (f": {est.failure}" if est.failure else "")
            s.reason = why if not s.used else f"round {s.rounds}: {why}"
            break
        s.take(res, alive)
        if candidates:
            t2 = time.perf_counter()
            s.restore(candidates, res, judged_now, est)
            s.seconds[-1]["restoring"] = time.perf_counter() - t2
        if set(res.trusted) >= set(res.registered):
            break  # every placed image judged already: another round changes little
        s.focus = {i for p in matches for i in p} - s.trusted
    return s.decision(matches)


#: Steps through the pair graph around the images a later round is for: the later estimate is
#: made from the surviving matches of the pairs among those images and the images this many
#: pairs away from them, so its cost follows the images left to judge, not the scene.
LATER_ROUND_RINGS = 2


def images_around(images: set[int], pairs, rings: int) -> set[int]:
    """``images`` and the images at most ``rings`` pairs away from them in ``pairs``."""
    neighbours: dict[int, set[int]] = {}
    for i, j in pairs:
        neighbours.setdefault(i, set()).add(j)
        neighbours.setdefault(j, set()).add(i)
    near, edge = set(images), set(images)
    for _ in range(rings):
        edge = {k for i in edge for k in neighbours.get(i, ())} - near
        near |= edge
    return near


@dataclass(frozen=True, kw_only=True)
class Judgement:
    """One judgement against one estimate (:func:`check_matches`), a step of a round; the check's
    result is :class:`MatchCheckDecision` (``failed``: pair -> bool ``(M,)`` over judged pairs;
    distances in pixels; ``poses``: those judged with, re-placed images' included)."""

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
    poses: dict[int, Pose] = field(default_factory=dict)


def check_matches(matches: Mapping[Pair, np.ndarray], rays: Mapping[int, np.ndarray],
                  focal: Mapping[int, float], poses: Mapping[int, Pose],
                  pair_rotations: Mapping[Pair, np.ndarray], cfg: MatchCheckConfig,
                  threshold: float | None = None) -> Judgement:
    """Judge the matches of every pair of two trusted images against the estimate.

    ``matches``: pair -> int ``(M, 2)`` keypoint indices; ``pair_rotations``: pair -> its own
    ``R_2from1``. ``threshold`` (pixels) replaces the one taken from these distances (later rounds).
    ``used`` is False when too few images, or too small a share, are trusted."""
    registered = frozenset(int(k) for k in poses)
    if len(registered) < cfg.min_trusted_images:
        return Judgement(used=False, registered=registered,
                                reason=f"the global estimate placed {len(registered)} images "
                                       f"(at least {cfg.min_trusted_images} needed)")
    trusted, agree, total = trusted_images(poses, pair_rotations, cfg.max_rotation_deg, cfg.min_agreeing_pairs)
    needed = max(cfg.min_trusted_images, int(np.ceil(cfg.min_trusted_share * len(registered))))
    if len(trusted) < needed:
        return Judgement(
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
            return Judgement(
                used=False, registered=registered, trusted=frozenset(trusted), cut_off=frozenset(cut),
                agreeing_pairs=agree, rotation_pairs=total,
                reason=f"removing the matches that fail the global estimate would cut {len(cut)} images off the "
                       f"rest of the pair graph; {len(trusted)} trusted images left ({needed} needed)")
    return Judgement(
        used=True, registered=registered, trusted=frozenset(trusted), cut_off=frozenset(cut), agreeing_pairs=agree,
        rotation_pairs=total, scale_px=scale, threshold_px=threshold, failed=failed, wrong_pairs=wrong,
        pair_fail_share=share, matches_judged=int(all_d.size),
        matches_failed=int(sum(int(f.sum()) for f in failed.values())), poses=dict(poses))


def robust_scale(distances: np.ndarray) -> float:
    """Mean ``b = median / ln 2`` of the distances modelled as exponential (a folded Laplace
    residual: keypoint errors have heavier tails than a normal's). Wrong matches only push the
    median up a little, so the threshold errs towards keeping. 0 for no distances."""
    d = np.asarray(distances, np.float64)
    d = d[np.isfinite(d)]
    return float(np.median(d)) / np.log(2.0) if d.size else 0.0


def threshold_px(scale: float, false_reject: float, lo: float, hi: float) -> float:
    """``scale * ln(1 / false_reject)`` clamped to ``[lo, hi]``."""
    return float(np.clip(scale * np.log(1.0 / false_reject), lo, hi))


def trusted_images(poses: Mapping[int, Pose], pair_rotations: Mapping[Pair, np.ndarray],
                   max_rotation_deg: float, min_agreeing_pairs: int
                   ) -> tuple[set[int], dict[int, int], dict[int, int]]:
    """The images whose estimated pose agrees with their pairs' own relative rotations.

    A pair's own rotation is arbitrary for a wrong pair, and wrong pairs are many on real scenes, so
    a median is not robust: an image is trusted when at least ``min_agreeing_pairs`` pairs agree
    within ``max_rotation_deg``. Returns (trusted ids, id -> agreeing pairs, id -> pairs with a
    rotation)."""
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
    """The largest connected component; of equal ones, the one holding the smallest node."""
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
    """The images of the pair graph's main part that removing failed matches and wrong pairs would
    cut off (a pair links its images with at least ``min_pair_matches`` matches)."""
    nodes = sorted({i for p in matches for i in p})
    before = [p for p, m in matches.items() if len(m) >= min_pair_matches]
    after = [p for p, m in matches.items() if p not in wrong
             and len(m) - (int(np.count_nonzero(failed[p])) if p in failed else 0) >= min_pair_matches]
    return _largest_component(before, nodes) - _largest_component(after, nodes)


#: Rounds of placing the untrusted images again: a placement made from a trusted part that
#: still held a group placed wrong together (which the split test then finds) is made again
#: from what is left.
PLACEMENT_ROUNDS = 3


def place_untrusted(estimator: Estimator[Est], est: Est, res: Judgement,
                    matches: Mapping[Pair, np.ndarray], cfg: MatchCheckConfig,
                    threshold: float | None) -> Judgement:
    """Place each untrusted image again from the trusted part's 3D points (as incremental mapping
    would, so its wrong pairs do not bend the estimate) and judge again; repeat for images that
    would be cut off, up to :data:`PLACEMENT_ROUNDS` times."""
    if not cfg.place_untrusted:
        return res
    poses = dict(est.poses)
    thr = res.threshold_px if threshold is None else threshold  # the first judgement's, kept
    cut = set(res.cut_off)
    before: frozenset[int] | None = None
    for _ in range(PLACEMENT_ROUNDS):
        if not res.used or res.trusted >= res.registered or res.trusted == before:
            break  # all trusted, or the last placement changed nothing
        before = res.trusted
        moved = False
        for k in sorted(res.registered - res.trusted):
            pose = estimator.place(est, k, matches, res.trusted)
            if pose is not None:
                poses[k], moved = pose, True
        if not moved:
            break
        res = check_matches(matches, est.rays, est.focal, poses, est.pair_rotations, cfg, threshold=thr)
        cut |= res.cut_off
    return dataclasses.replace(res, cut_off=frozenset(cut))
