"""Match-check stage: after the filter (and the pair check), before the refinement, judge every
match against a global estimate of the cameras (:mod:`colmap_miho.verification.match_check`)
and remove the ones it contradicts, so that the track walk refines only what survives.

The estimate is pycolmap's global mapper on the filtered matches, run once in this process
(:func:`colmap_miho.adapters.global_model.global_estimate`). With ``rounds`` > 1 the estimate is
made again from the survivors: an image whose first pose the check did not trust (placed wrong
by the wrong matches of its pairs) can be trusted and judged in the next round.

What the stage decides is kept in the run store (``stage-match_check.npz``): a resumed run reads
it back instead of running the mapper again (its result is not bit-for-bit repeatable across
thread counts). Matches of filtered pairs that failed are taken out of the pair's kept matches
(:meth:`MatchCheckOutcome.apply`); wrong pairs are removed whole (filtered or not), like the
pair check's; every judged pair's geometry is fitted again from its survivors when written.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from ..adapters.database import ColmapDatabase
from ..enums import MatchCheckMode, MatchSource
from ..verification.config import MatchCheckConfig
from ..verification.match_check import MatchCheckResult, check_matches
from .pair_check import pair_graph_matches
from .records import FilteredPairs, PairOutcome
from .store import RunStore

log = logging.getLogger(__name__)

#: A pair of image ids (image_id1 < image_id2).
Pair = tuple[int, int]

#: Name of the stage's result in the run store.
STORE_NAME = "match_check"

#: Most wrong pairs listed by name in the stats (all are counted).
MAX_LISTED_PAIRS = 200


@dataclass(frozen=True, kw_only=True)
class MatchCheckStats:
    """What the match check did (``RefineSummary.match_check``; empty when it is off).

    Attributes:
        mode: "remove" or "flag".
        used: the global estimate was trusted and the matches judged (in some round).
        reason: why it was not used ("" when used).
        rounds: estimates made.
        images: images in the pair graph; images_registered: placed by the (last) estimate.
        images_trusted / images_untrusted: names of the placed images whose pose the check
            trusted / did not trust (their pairs were not judged), over the rounds.
        images_cut_off: names of the images that agreed with their pairs but that the
            removals would have cut off the rest of the pair graph (placed wrong as a group),
            so were not trusted at first (placed again, they may be trusted after all).
        scale_px / threshold_px: the first round's exponential scale of the distances and
            threshold (pixels), which every round applies.
        matches_checked: matches in the pair graph; matches_judged: of those, in pairs of two
            trusted images.
        matches_removed: matches of kept pairs that failed (removed in "remove" mode).
        pairs_removed: pairs most of whose matches failed (removed whole), with
            ``matches_in_removed_pairs`` matches.
        wrong_pairs: the first :data:`MAX_LISTED_PAIRS` of those: image names and ids, matches,
            share failing.
        seconds: wall time of the global estimates (the rest of the stage is small).
    """

    mode: str
    used: bool
    reason: str
    rounds: int
    images: int
    images_registered: int
    images_trusted: list[str] = field(default_factory=list)
    images_untrusted: list[str] = field(default_factory=list)
    images_cut_off: list[str] = field(default_factory=list)
    scale_px: float = 0.0
    threshold_px: float = 0.0
    matches_checked: int = 0
    matches_judged: int = 0
    matches_removed: int = 0
    pairs_removed: int = 0
    matches_in_removed_pairs: int = 0
    wrong_pairs: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """Plain JSON-ready data."""
        out = dataclasses.asdict(self)
        for k in ("scale_px", "threshold_px", "seconds"):
            out[k] = round(float(out[k]), 3)
        return out


@dataclass(frozen=True, kw_only=True)
class MatchCheckOutcome:
    """What the later stages apply.

    Attributes:
        failed: pair -> bool ``(K,)`` over the pair's kept matches (in the order of
            ``inliers``' set rows): the ones removed.
        wrong: pairs removed whole.
        refit: pairs whose geometry is fitted again from the survivors when written.
    """

    failed: dict[Pair, np.ndarray] = field(default_factory=dict)
    wrong: frozenset[Pair] = frozenset()
    refit: frozenset[Pair] = frozenset()

    def apply(self, pairs: FilteredPairs) -> FilteredPairs:
        """``pairs`` with the failed matches taken out of each pair's kept matches (their
        ``inliers`` cleared, labels -1); other pairs unchanged."""
        if not self.failed:
            return pairs
        out = dict(pairs)
        for key, (m, r) in pairs.items():
            f = self.failed.get(key)
            if f is None or not f.any():
                continue
            rows = np.flatnonzero(r.inliers)[f]
            inl = np.array(r.inliers, bool)
            lab = np.array(r.labels, np.int64)
            inl[rows], lab[rows] = False, -1
            out[key] = (m, PairOutcome(inliers=inl, labels=lab, patch_homographies=r.patch_homographies,
                                       success=r.success))
        return out


def run_match_check(db: ColmapDatabase, store: RunStore, cfg: MatchCheckConfig, source: MatchSource, *,
                    removed: set[Pair], threads: int = -1
                    ) -> tuple[MatchCheckOutcome, MatchCheckStats | None]:
    """The stage: judge the pair graph's matches (the ``removed`` pairs left out); returns what
    to apply (nothing in "flag" mode) and the stats (None when off)."""
    if not cfg.enabled:
        return MatchCheckOutcome(), None
    stored = store.load_stage(STORE_NAME)
    if stored is None:
        failed, wrong, meta = _decide(db, store, cfg, source, removed, threads)
        store.save_stage(STORE_NAME, _pack(failed, wrong), meta)
    else:
        failed, wrong = _unpack(*stored[:1])
        meta = stored[1]
        log.info("match check: the verdicts of the interrupted run are used")
    stats = MatchCheckStats(**meta)
    for w in stats.wrong_pairs:
        log.info("match check: %s %s - %s: %.0f%% of %d matches off the global estimate",
                 "removed" if cfg.mode == MatchCheckMode.REMOVE else "flagged", *w["images"],
                 100 * w["fail_share"], w["matches"])
    if cfg.mode != MatchCheckMode.REMOVE or not stats.used:
        return MatchCheckOutcome(), stats
    filtered = set(store.load_filtered())
    return (MatchCheckOutcome(failed={p: f for p, f in failed.items() if p in filtered and p not in wrong},
                              wrong=frozenset(wrong), refit=frozenset(p for p in failed if p in filtered)),
            stats)


def _decide(db: ColmapDatabase, store: RunStore, cfg: MatchCheckConfig, source: MatchSource,
            removed: set[Pair], threads: int) -> tuple[dict[Pair, np.ndarray], set[Pair], dict]:
    """The rounds of estimate and judgement; returns (pair -> failed mask over its matches,
    wrong pairs, the stats' fields)."""
    from ..adapters.global_model import global_estimate

    matches = {p: m for p, m in pair_graph_matches(db, store, source).items() if p not in removed}
    names = {im.image_id: im.name for im in db.images()}
    failed = {p: np.zeros(len(m), bool) for p, m in matches.items()}
    wrong: set[Pair] = set()
    trusted_any: set[int] = set()
    registered_any: set[int] = set()
    cut_any: set[int] = set()
    used, reason, scale, threshold, seconds, rounds, registered = False, "", 0.0, 0.0, 0.0, 0, 0
    for _ in range(cfg.rounds):
        alive = {p: np.flatnonzero(~f) for p, f in failed.items() if p not in wrong and (~f).any()}
        current = {p: matches[p][idx] for p, idx in alive.items()}
        t0 = time.perf_counter()
        est = global_estimate(db, current, min_pair_matches=cfg.min_pair_matches, seed=cfg.seed,
                              num_threads=threads, ba_iterations=cfg.ba_iterations, retriangulate=cfg.retriangulate)
        seconds += time.perf_counter() - t0
        rounds += 1
        res = check_matches(current, est.rays, est.focal, est.poses, est.pair_rotations, cfg,
                            threshold=threshold if used else None)
        res = _place_untrusted(est, res, current, cfg, threshold if used else None)
        cut_any |= set(res.cut_off)  # the first judgement's and the placements' together
        registered = len(res.registered)
        registered_any |= set(res.registered)
        if not res.used:
            reason = reason or res.reason
            break
        if not used:
            scale, threshold = res.scale_px, res.threshold_px
        used, reason = True, ""
        for p, f in res.failed.items():  # a later round judges only the pairs of images newly trusted
            if not (p[0] in trusted_any and p[1] in trusted_any):
                failed[p][alive[p][f]] = True
        trusted_any |= set(res.trusted)
        wrong |= set(res.wrong_pairs)
        if set(res.trusted) >= set(res.registered):
            break  # every placed image judged already: another round changes little
    judged_pairs = {p for p in matches if p[0] in trusted_any and p[1] in trusted_any}
    share = {p: float(failed[p].mean()) for p in wrong}  # before the pair is removed whole
    for p in wrong:
        failed[p][:] = True
    wrong_list = sorted(wrong, key=lambda p: (-len(matches[p]), p))
    meta = {
        "mode": str(cfg.mode), "used": used, "reason": reason, "rounds": rounds,
        "images": len({i for p in matches for i in p}), "images_registered": registered,
        "images_trusted": sorted(names.get(i, str(i)) for i in trusted_any),
        "images_untrusted": sorted(names.get(i, str(i)) for i in registered_any - trusted_any),
        "images_cut_off": sorted(names.get(i, str(i)) for i in cut_any),
        "scale_px": scale, "threshold_px": threshold,
        "matches_checked": int(sum(len(m) for m in matches.values())),
        "matches_judged": int(sum(len(matches[p]) for p in judged_pairs)),
        "matches_removed": int(sum(int(f.sum()) for p, f in failed.items() if p not in wrong)),
        "pairs_removed": len(wrong), "matches_in_removed_pairs": int(sum(len(matches[p]) for p in wrong)),
        "wrong_pairs": [{"images": [names.get(i, str(i)), names.get(j, str(j))], "image_ids": [i, j],
                         "matches": len(matches[(i, j)]), "fail_share": round(share[(i, j)], 3)}
                        for i, j in wrong_list[:MAX_LISTED_PAIRS]],
        "seconds": seconds,
    }
    return ({p: f for p, f in failed.items() if f.any() or p in judged_pairs}, wrong, meta)


#: Rounds of placing the untrusted images again: a placement made from a trusted part that
#: still held a group placed wrong together (which the split test then finds) is made again
#: from what is left.
PLACEMENT_ROUNDS = 3


def _place_untrusted(est, res: MatchCheckResult, matches: dict[Pair, np.ndarray], cfg: MatchCheckConfig,
                     threshold: float | None) -> MatchCheckResult:
    """Place each registered image the check did not trust again, from the estimate's 3D
    points its keypoints match through the trusted images (as incremental mapping registers an
    image: the trusted part of the estimate is not bent by that image's wrong pairs), and judge
    again with those poses (the trust test decides again whether each new pose holds). When
    that judgement finds images that would be cut off (:func:`cut_off_images`), they are placed
    again from the smaller trusted part, up to :data:`PLACEMENT_ROUNDS` times."""
    from ..adapters.global_model import place_by_points

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
            pose = place_by_points(est, k, matches, res.trusted, max_error_px=cfg.max_threshold_px,
                                   min_inliers=cfg.min_placed_inliers, seed=cfg.seed)
            if pose is not None:
                poses[k], moved = pose, True
        if not moved:
            break
        res = check_matches(matches, est.rays, est.focal, poses, est.pair_rotations, cfg, threshold=thr)
        cut |= res.cut_off
    return dataclasses.replace(res, cut_off=frozenset(cut))


def _pack(failed: dict[Pair, np.ndarray], wrong: set[Pair]) -> dict[str, np.ndarray]:
    keys = sorted(failed)
    return {"pairs": np.asarray(keys, np.int64).reshape(-1, 2),
            "offsets": np.concatenate([[0], np.cumsum([len(failed[k]) for k in keys])]).astype(np.int64),
            "failed": np.concatenate([failed[k] for k in keys]) if keys else np.zeros(0, bool),
            "wrong": np.asarray(sorted(wrong), np.int64).reshape(-1, 2)}


def _unpack(arrays: dict[str, np.ndarray]) -> tuple[dict[Pair, np.ndarray], set[Pair]]:
    pairs, off, f = arrays["pairs"], arrays["offsets"], arrays["failed"]
    failed = {(int(a), int(b)): f[off[k]:off[k + 1]].astype(bool) for k, (a, b) in enumerate(pairs)}
    return failed, {(int(a), int(b)) for a, b in arrays["wrong"]}
