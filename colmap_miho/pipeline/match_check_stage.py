"""Match-check stage: after the filter, before the refinement, judge every
match against a global estimate of the cameras (:mod:`colmap_miho.verification.match_check`)
and remove the ones it contradicts, so that the track walk refines only what survives.

The check itself, rounds and re-placements included, is
:func:`colmap_miho.verification.match_check.judge_in_rounds`; its estimator is pycolmap's global
mapper on the filtered matches, run in this process
(:class:`colmap_miho.sfm.global_estimate.GlobalEstimator`). This stage reads the matches, keeps
the verdicts, names the images in the stats and says what the later stages apply.

What the stage decides is kept in the run store (``stage-match_check.npz``): a resumed run reads
it back instead of running the mapper again (its result is not bit-for-bit repeatable across
thread counts). What it returns (:class:`~.verdicts.Verdicts`): the matches of filtered pairs
that failed, taken out of the pair's kept matches; the wrong pairs, removed whole (filtered or
not); the judged pairs, whose geometry is fitted again from their
survivors when written.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..adapters.database import ColmapDatabase
from ..enums import MatchCheckMode, MatchSource
from ..seeds import match_check_seed
from ..types import Pair
from ..verification.config import MatchCheckConfig
from ..verification.hinge import HingeVerdict
from ..verification.match_check import MatchCheckDecision, judge_in_rounds
from .store import RunStore
from .store_checks import StoreDamaged, check_array, check_offsets, check_unique_pairs
from .verdicts import NO_VERDICTS, Verdicts, pair_graph

log = logging.getLogger(__name__)

#: Name of the stage's result in the run store.
STORE_NAME = "match_check"

#: Most wrong pairs listed by name in the stats (all are counted).
MAX_LISTED_PAIRS = 200


@dataclass(frozen=True, kw_only=True)
class MatchCheckStats:
    """What the match check did (``RefineSummary.match_check``; empty when off): whether the
    estimate was used and why not, the images trusted, untrusted and cut off, the first round's
    scale and threshold (pixels), the matches and pairs removed, per-pair removals, the matches
    the filter removed that it restored (``pairs_revived``: pairs the filter had emptied), peak
    memory (MiB), per-round seconds and the hinges found with their verdicts."""

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
    removed_per_pair: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    peak_rss_mb: float = 0.0
    round_seconds: list[dict] = field(default_factory=list)
    mapper_steps: list[dict] = field(default_factory=list)
    hinges: list[dict] = field(default_factory=list)
    matches_restored: int = 0
    pairs_restored: int = 0
    pairs_revived: int = 0
    restored_per_pair: list[dict] = field(default_factory=list)

    @classmethod
    def of(cls, d: MatchCheckDecision, cfg: MatchCheckConfig, matches: dict[Pair, np.ndarray],
           names: dict[int, str], restored: dict[Pair, np.ndarray] | None = None) -> MatchCheckStats:
        """The stats of the check's decision ``d`` on ``matches``, images named (``restored``:
        pair -> the rows given back)."""
        def name(i: int) -> str:
            return names.get(i, str(i))

        restored = restored or {}
        wrong_list = sorted(d.wrong, key=lambda p: (-len(matches[p]), p))
        return cls(
            mode=str(cfg.mode), used=d.used, reason=d.reason, rounds=d.rounds,
            images=len({i for p in matches for i in p}), images_registered=len(d.registered),
            images_trusted=sorted(name(i) for i in d.trusted),
            images_untrusted=sorted(name(i) for i in d.untrusted),
            images_cut_off=sorted(name(i) for i in d.cut_off),
            scale_px=d.scale_px, threshold_px=d.threshold_px,
            matches_checked=int(sum(len(m) for m in matches.values())),
            matches_judged=int(sum(len(matches[p]) for p in d.judged_pairs)),
            matches_removed=int(sum(int(f.sum()) for p, f in d.failed.items() if p not in d.wrong)),
            pairs_removed=len(d.wrong), matches_in_removed_pairs=int(sum(len(matches[p]) for p in d.wrong)),
            wrong_pairs=[{"images": [name(i), name(j)], "image_ids": [i, j], "matches": len(matches[(i, j)]),
                          "fail_share": round(d.fail_share[(i, j)], 3)} for i, j in wrong_list[:MAX_LISTED_PAIRS]],
            removed_per_pair=[{"images": [name(i), name(j)], "image_ids": [i, j], "removed": int(f.sum())}
                              for (i, j), f in sorted(d.failed.items()) if f.any()],
            seconds=float(sum(sum(r.values()) for r in d.seconds)), round_seconds=d.seconds,
            mapper_steps=d.mapper_steps,
            peak_rss_mb=_peak_rss_mb(),
            hinges=[_hinge_meta(h, matches, name) for h in d.hinges],
            matches_restored=int(sum(len(r) for r in restored.values())),
            pairs_restored=len(restored),
            pairs_revived=sum(1 for p in restored if p not in matches),
            restored_per_pair=[{"images": [name(i), name(j)], "image_ids": [i, j], "restored": len(r)}
                               for (i, j), r in sorted(restored.items())],
        )

    def to_dict(self) -> dict:
        """Plain JSON-ready data."""
        out = dataclasses.asdict(self)
        for k in ("scale_px", "threshold_px", "seconds", "peak_rss_mb"):
            out[k] = round(float(out[k]), 3)
        for key in ("round_seconds", "mapper_steps"):
            out[key] = [{k: round(float(v), 3) for k, v in r.items()} for r in getattr(self, key)]
        return out


def run_match_check(db: ColmapDatabase, store: RunStore, cfg: MatchCheckConfig, source: MatchSource, *,
                    seed: int = 0, threads: int = -1) -> tuple[Verdicts, MatchCheckStats | None]:
    """The stage: judge the pair graph's matches (``seed``: the run's root seed); returns its
    :class:`~.verdicts.Verdicts` (none in "flag" mode) and the stats (None when off)."""
    if not cfg.enabled:
        return NO_VERDICTS, None
    stored = store.load_stage(STORE_NAME)
    if stored is None:
        failed, wrong, restored, stats = _decide(db, store, cfg, source, seed, threads)
        store.save_stage(STORE_NAME, _pack(failed, wrong, restored), dataclasses.asdict(stats))
    else:
        failed, wrong, restored, stats = _read_back(store, *stored)
        log.info("match check: the verdicts of the interrupted run are used")
    if not stats.used:  # every way the check switches itself off is said, also under -q
        log.warning("match check: not used, nothing %s: %s", "removed" if cfg.mode == MatchCheckMode.REMOVE
                    else "flagged", stats.reason)
    for w in stats.wrong_pairs:
        log.debug("match check: %s %s - %s: %.0f%% of %d matches off the global estimate",
                 "removed" if cfg.mode == MatchCheckMode.REMOVE else "flagged", *w["images"],
                 100 * w["fail_share"], w["matches"])
    if cfg.mode != MatchCheckMode.REMOVE or not stats.used:
        return NO_VERDICTS, stats
    filtered = store.load_filtered()
    known = {(p.image_id1, p.image_id2) for p in db.pairs(source)}

    def judged_rows(pair: Pair) -> int:
        """The matches the verdict on ``pair`` was made on (-1: no pair of the run)."""
        if pair in filtered:
            return int(np.count_nonzero(filtered[pair][1].inliers))
        return len(db.matches(pair[0], pair[1], source)) if pair in known else -1

    if any(len(f) != judged_rows(p) for p, f in failed.items() if p not in wrong):
        raise StoreDamaged(store.folder / f"stage-{STORE_NAME}.npz", "its verdicts do not fit the stored pairs")
    if not all(_restorable(filtered.get(p), r) and p not in wrong for p, r in restored.items()):
        raise StoreDamaged(store.folder / f"stage-{STORE_NAME}.npz", "its restored matches do not fit the stored pairs")
    judged = {p: f for p, f in failed.items() if p not in wrong}
    # a pair written back unchanged keeps COLMAP's model where the check removed nothing from it
    return (Verdicts(removed=frozenset(wrong), failed=judged, restored=restored,
                     refit=frozenset(p for p, f in judged.items() if p in filtered or f.any()) | frozenset(restored)),
            stats)


def _restorable(stored, rows: np.ndarray) -> bool:
    """Whether ``rows`` index matches a stored filter outcome ``(m, r)`` removed."""
    if stored is None:
        return False
    inliers = np.asarray(stored[1].inliers, bool)
    return bool(len(rows) == 0 or (int(rows.max()) < len(inliers) and not inliers[rows].any()))


def _decide(db: ColmapDatabase, store: RunStore, cfg: MatchCheckConfig, source: MatchSource, seed: int,
            threads: int) -> tuple[dict[Pair, np.ndarray], frozenset[Pair], dict[Pair, np.ndarray], MatchCheckStats]:
    """The check on the pair graph: (pair -> failed mask, wrong pairs, filtered pair -> its stored
    rows restored, the stats)."""
    from ..sfm.global_estimate import GlobalEstimator
    from ..sfm.mapping import release_freed_heap

    filtered = store.load_filtered()
    matches = pair_graph(db, filtered, source)
    # the matches the filter removed, offered back to the check
    removed_rows = {p: np.flatnonzero(~np.asarray(r.inliers, bool)) for p, (m, r) in filtered.items()}
    candidates = {p: np.asarray(filtered[p][0][rows], np.int64) for p, rows in removed_rows.items() if len(rows)}
    del filtered  # not held during the mapper: only the kept matches and the candidates are
    estimator = GlobalEstimator(src=db, config=cfg, seed=match_check_seed(seed), num_threads=threads,
                                verbose=log.isEnabledFor(logging.DEBUG))  # -v: COLMAP's log on the terminal
    d = judge_in_rounds(matches, estimator, cfg, candidates)
    release_freed_heap()  # the judging's and restoring's, before the refinement
    restored = {p: removed_rows[p][ok] for p, ok in sorted(d.restored.items())}
    names = {im.image_id: im.name for im in db.images()}
    return d.failed, d.wrong, restored, MatchCheckStats.of(d, cfg, matches, names, restored)


def _hinge_meta(v: HingeVerdict, matches: dict[Pair, np.ndarray], name) -> dict:
    """The stats' record of one hinge, images named."""
    def named(pairs) -> list[list[str]]:
        return [[name(i), name(j)] for i, j in sorted(pairs)]

    def median(scores: dict) -> float:
        values = [x for x in scores.values() if np.isfinite(x)]
        return round(float(np.median(values)), 3) if values else 0.0

    h, g = v.hinge, v.groups
    return {"round": v.round, "angle_deg": round(h.angle_deg, 1),
            "images_a": sorted(name(i) for i in g.side_a), "images_b": sorted(name(i) for i in g.side_b),
            "estimate_pairs": named(g.across), "mode_pairs": named(h.mode_pairs),
            "estimate_coverage": median(v.estimate_coverage), "mode_coverage": median(v.mode_coverage),
            "verdict": v.verdict, "action": v.action, "pairs_unjudged": len(v.unjudged),
            "matches_unjudged": int(sum(len(matches[p]) for p in v.unjudged if p in matches))}


def _peak_rss_mb() -> float:
    """Peak resident memory so far in MiB (``VmHWM``: ``ru_maxrss`` would carry the launcher's
    across ``exec``); 0 when unreadable."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError):
        pass
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return 0.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _pack(failed: dict[Pair, np.ndarray], wrong: frozenset[Pair], restored: dict[Pair, np.ndarray]
          ) -> dict[str, np.ndarray]:
    keys = sorted(failed)
    back = sorted(restored)
    return {"pairs": np.asarray(keys, np.int64).reshape(-1, 2),
            "offsets": np.concatenate([[0], np.cumsum([len(failed[k]) for k in keys])]).astype(np.int64),
            "failed": np.concatenate([failed[k] for k in keys]) if keys else np.zeros(0, bool),
            "wrong": np.asarray(sorted(wrong), np.int64).reshape(-1, 2),
            "restored_pairs": np.asarray(back, np.int64).reshape(-1, 2),
            "restored_offsets": np.concatenate([[0], np.cumsum([len(restored[k]) for k in back])]).astype(np.int64),
            "restored_rows": (np.concatenate([restored[k] for k in back]) if back else np.zeros(0)).astype(np.int64)}


def _read_back(store: RunStore, arrays: dict[str, np.ndarray], meta: dict
               ) -> tuple[dict[Pair, np.ndarray], frozenset[Pair], dict[Pair, np.ndarray], MatchCheckStats]:
    """The stored verdicts and stats of an interrupted run; StoreDamaged for another layout."""
    path = store.folder / f"stage-{STORE_NAME}.npz"
    failed, wrong, restored = _unpack(arrays, path)
    _check_meta(meta, path)
    try:
        stats = MatchCheckStats(**meta)
        if not all(np.asarray(f).ndim == 1 for f in failed.values()):
            raise ValueError("a verdict is not one row of flags")
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise StoreDamaged(path, f"{type(exc).__name__}: {exc}") from None
    return failed, wrong, restored, stats


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


#: What each annotation of :class:`MatchCheckStats` takes in JSON.
_META_TYPES = {
    "str": lambda v: isinstance(v, str), "bool": lambda v: isinstance(v, bool),
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool), "float": _is_number,
    "list[str]": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
    "list[dict]": lambda v: isinstance(v, list) and all(isinstance(x, dict) for x in v),
}


def _check_meta(meta: dict, path: Path) -> None:
    """The stored stats checked against :class:`MatchCheckStats`'s field types; StoreDamaged otherwise."""
    for f in dataclasses.fields(MatchCheckStats):
        if f.name in meta and not _META_TYPES[str(f.type)](meta[f.name]):
            raise StoreDamaged(path, f"its stats' {f.name} is not of type {f.type}")
    for w in meta.get("wrong_pairs", []):
        images = w.get("images")
        if not (isinstance(images, list) and len(images) == 2 and _is_number(w.get("fail_share"))
                and _is_number(w.get("matches"))):
            raise StoreDamaged(path, "its stats' wrong_pairs do not name two images, a share and matches")
    for key in ("round_seconds", "mapper_steps"):
        if not all(_is_number(v) for r in meta.get(key, []) for v in r.values()):
            raise StoreDamaged(path, f"its stats' {key} are not all numbers")


def _unpack(arrays: dict[str, np.ndarray], path: Path
            ) -> tuple[dict[Pair, np.ndarray], frozenset[Pair], dict[Pair, np.ndarray]]:
    """The verdicts of :func:`_pack`'s arrays, checked; StoreDamaged for another layout."""
    pairs = check_array(arrays, "pairs", path, "iu", (None, 2))
    f = check_array(arrays, "failed", path, "b", (None,))
    off = check_array(arrays, "offsets", path, "iu", (len(pairs) + 1,))
    check_offsets(off, len(f), "offsets", path)
    wrong = check_array(arrays, "wrong", path, "iu", (None, 2))
    check_unique_pairs(pairs, path)
    check_unique_pairs(wrong, path, "wrong pairs")
    failed = {(int(a), int(b)): f[off[k]:off[k + 1]] for k, (a, b) in enumerate(pairs.tolist())}
    back = check_array(arrays, "restored_pairs", path, "iu", (None, 2))
    rows = check_array(arrays, "restored_rows", path, "iu", (None,))
    roff = check_array(arrays, "restored_offsets", path, "iu", (len(back) + 1,))
    check_offsets(roff, len(rows), "restored_offsets", path)
    check_unique_pairs(back, path, "restored pairs")
    if len(rows) and int(rows.min()) < 0:
        raise StoreDamaged(path, "its restored rows are not row indices")
    restored = {(int(a), int(b)): rows[roff[k]:roff[k + 1]].astype(np.int64) for k, (a, b) in enumerate(back.tolist())}
    return failed, frozenset((int(a), int(b)) for a, b in wrong.tolist()), restored
