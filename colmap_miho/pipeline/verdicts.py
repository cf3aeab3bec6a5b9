"""The checks' verdicts, and the matches that reach the output database once they are applied.

The match check (:mod:`.match_check`) returns one :class:`Verdicts`; the later stages apply it
with its one method
(:meth:`Verdicts.apply`): the refine stage to the stored pairs it walks, the write stage to each
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
    """What the checks decided about the pairs that reach the output.

    Attributes:
        removed: pairs removed whole (the match check's wrong pairs):
            they join no track and are written without matches or two-view geometry, whether
            they were filtered or not.
        failed: pair -> bool ``(K,)``: the matches the match check removed from a kept pair,
            over its kept matches (in the order of its ``inliers``' set rows) for a filtered
            pair, over the database's matches for a pair written back otherwise unchanged (too
            small to filter, or no plane found).
        refit: pairs the match check judged: their fundamental matrix is fitted again to the
            survivors when written (COLMAP's was fitted to the wrong matches too).
    """

    removed: frozenset[Pair] = frozenset()
    failed: Mapping[Pair, np.ndarray] = field(default_factory=dict)
    refit: frozenset[Pair] = frozenset()

    def apply(self, pairs: FilteredPairs) -> FilteredPairs:
        """``pairs`` without the removed ones and with failed matches cleared (labels -1)."""
        out = {k: v for k, v in pairs.items() if k not in self.removed} if self.removed else dict(pairs)
        for key, (m, r) in out.items():
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
