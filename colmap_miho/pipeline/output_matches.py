"""The matches that reach the output database, pair by pair, once the checks' verdicts are
applied: the one place the refine stage (its unrefined matches) and both checks (their pair
graph) take them from.

A pair's output matches are the kept matches of its stored filter outcome when it was
filtered (after the match check's :meth:`~.match_check.MatchCheckOutcome.apply`, which takes
the failed matches out of them), else the database's matches (a pair too small to filter, or
in which no plane was found: written back unchanged). Pairs removed whole (the pair check's and
the match check's wrong pairs) reach the output without matches.
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from ..adapters.database import ColmapDatabase
from ..enums import MatchSource
from ..types import Pair
from .records import FilteredPairs


def output_matches(db: ColmapDatabase, filtered: FilteredPairs, source: MatchSource, *,
                   removed: Collection[Pair] = ()) -> dict[Pair, np.ndarray]:
    """Every pair's output matches ``(M, 2)`` (the ``removed`` pairs left out; empty pairs
    kept), in the database's pair order."""
    out = {}
    for p in db.pairs(source):
        key = (p.image_id1, p.image_id2)
        if key in removed:
            continue
        if key in filtered:
            m, r = filtered[key]
            out[key] = m[np.asarray(r.inliers, bool)]
        else:
            out[key] = db.matches(p.image_id1, p.image_id2, source)
    return out


def pair_graph(db: ColmapDatabase, filtered: FilteredPairs, source: MatchSource, *,
               removed: Collection[Pair] = ()) -> dict[Pair, np.ndarray]:
    """The checks' pair graph: :func:`output_matches` as int64, pairs without matches left out."""
    return {k: np.asarray(v, np.int64) for k, v in output_matches(db, filtered, source, removed=removed).items()
            if len(v)}
