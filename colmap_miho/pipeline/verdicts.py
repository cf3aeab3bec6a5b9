"""The checks' verdicts, and the matches that reach the output database once they are applied.

The match check (:mod:`.match_check_stage`) returns one :class:`Verdicts`; the later stages apply it
with its one method
(:meth:`Verdicts.apply`): the keypoint refinement to the stored pairs it walks, the write stage to each
stored chunk it writes.

A pair's output matches (:func:`output_matches`) are the kept matches of its stored filter
outcome when it was filtered (the failed matches taken out), else the database's matches (a pair
too small to filter, or in which no plane was found), less the matches the match check
failed in it. Pairs removed whole reach the output without matches.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..adapters.database import ColmapDatabase
from ..enums import MatchSource
from ..types import Pair
from .records import FilteredPairs, PairOutcome


@dataclass(frozen=True, kw_only=True)
class Verdicts:
    """What the checks decided: pairs ``removed`` whole, ``failed`` matches per kept pair (bool
    ``(K,)``), pairs to ``refit`` (their fundamental matrix fitted again to the survivors) and the
    filter's removals ``restored`` (filtered pair -> rows of its stored matches)."""

    removed: frozenset[Pair] = frozenset()
    failed: Mapping[Pair, np.ndarray] = field(default_factory=dict)
    refit: frozenset[Pair] = frozenset()
    restored: Mapping[Pair, np.ndarray] = field(default_factory=dict)

    def apply(self, pairs: FilteredPairs) -> FilteredPairs:
        """``pairs`` without the removed ones, failed matches cleared and restored ones set (labels -1)."""
        out = {k: v for k, v in pairs.items() if k not in self.removed} if self.removed else dict(pairs)
        for key, (m, r) in out.items():
            f = self.failed.get(key)
            back = self.restored.get(key)
            if (f is None or not f.any()) and (back is None or not len(back)):
                continue
            inl = np.array(r.inliers, bool)
            lab = np.array(r.labels, np.int64)
            if f is not None and f.any():
                rows = np.flatnonzero(r.inliers)[f]
                inl[rows], lab[rows] = False, -1
            if back is not None and len(back):
                inl[back], lab[back] = True, -1
            out[key] = (m, PairOutcome(inliers=inl, labels=lab, patch_homographies=r.patch_homographies,
                                       success=r.success))
        return out


#: No verdicts: every pair as the filter left it.
NO_VERDICTS = Verdicts()


def output_matches(db: ColmapDatabase, kept: FilteredPairs, source: MatchSource,
                   verdicts: Verdicts = NO_VERDICTS) -> dict[Pair, np.ndarray]:
    """Every pair's output matches ``(M, 2)`` in database order (removed pairs left out, empty ones kept)."""
    out = {}
    for p in db.pairs(source):
        key = (p.image_id1, p.image_id2)
        if key in verdicts.removed:
            continue
        if key in kept:
            m, r = kept[key]
            out[key] = m[np.asarray(r.inliers, bool)]
        else:
            out[key] = unfiltered_matches(db, key, source, verdicts)
    return out


def unfiltered_matches(db: ColmapDatabase, pair: Pair, source: MatchSource, verdicts: Verdicts) -> np.ndarray:
    """A pair the filter did not keep: the database's matches less those ``verdicts`` failed."""
    m = db.matches(pair[0], pair[1], source)
    f = verdicts.failed.get(pair)
    return m if f is None else m[~f]


def pair_graph(db: ColmapDatabase, filtered: FilteredPairs, source: MatchSource,
               verdicts: Verdicts = NO_VERDICTS) -> dict[Pair, np.ndarray]:
    """The checks' pair graph: output matches of ``filtered`` with ``verdicts`` applied, int64, non-empty."""
    return {k: np.asarray(v, np.int64) for k, v in output_matches(db, verdicts.apply(filtered), source,
                                                                   verdicts).items() if len(v)}
