"""Pair-check stage: after the filter, before the refinement, find the pairs the rest of the pair
graph contradicts (:func:`colmap_miho.verification.check_pairs`) and remove or flag them.

The graph is every pair that reaches the output database: the filtered pairs' kept matches
(from the run store) and the pairs written back unchanged (too small to filter, or no plane
found; from the database). The check is deterministic and cheap, so a resumed run computes it
again from the stored filter chunks instead of storing it. Removed pairs are left out of the
refinement (their matches join no track) and written back without matches or geometry.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

from ..adapters.database import ColmapDatabase
from ..enums import MatchSource, PairCheckMode
from ..verification import PairCheckConfig, check_pairs
from .read import ReadOutput
from .store import RunStore
from .verdicts import NO_VERDICTS, Verdicts, pair_graph

log = logging.getLogger(__name__)

@dataclass(frozen=True, kw_only=True)
class PairCheckStats:
    """What the pair check did (``RefineSummary.pair_check``; empty when it is off).

    Attributes:
        mode: "remove" or "flag".
        pairs_checked: pairs in the graph (all that reach the output).
        triangles / triangles_broken: triangles of the pair graph, and those in which every
            pair's transfers mostly fail.
        pairs_removed / pairs_flagged: pairs found wrong (removed in "remove" mode, only
            reported in "flag" mode).
        wrong_pairs: one entry per pair found wrong, in the order found: image names and ids,
            the reason and the scores of :class:`~colmap_miho.verification.PairVerdict`.
    """

    mode: str
    pairs_checked: int
    triangles: int
    triangles_broken: int
    pairs_removed: int
    pairs_flagged: int
    wrong_pairs: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        """Plain JSON-ready data."""
        return dataclasses.asdict(self)


def run_pair_check(db: ColmapDatabase, read: ReadOutput, store: RunStore, cfg: PairCheckConfig,
                   source: MatchSource) -> tuple[Verdicts, PairCheckStats | None]:
    """Check the pair graph; returns the :class:`~.verdicts.Verdicts` (the pairs to remove;
    none when off or in "flag" mode) and the stage's :class:`PairCheckStats` (None when off)."""
    if not cfg.enabled:
        return NO_VERDICTS, None
    matches = pair_graph(db, store.load_filtered(), source)
    result = check_pairs(matches, read.keypoints, cfg)
    names = {im.image_id: im.name for im in db.images()}
    wrong = [{"images": [names.get(i, str(i)), names.get(j, str(j))], "image_ids": [i, j],
              **result.verdicts[(i, j)].to_dict()} for i, j in result.wrong]
    remove = cfg.mode == PairCheckMode.REMOVE
    stats = PairCheckStats(mode=str(cfg.mode), pairs_checked=len(matches), triangles=result.triangles,
                           triangles_broken=result.triangles_broken,
                           pairs_removed=len(wrong) if remove else 0, pairs_flagged=0 if remove else len(wrong),
                           wrong_pairs=wrong)
    for w in wrong:
        log.info("pair check: %s %s - %s: %s", "removed" if remove else "flagged", *w["images"], w["reason"])
    return (Verdicts(removed=frozenset(result.wrong)) if remove else NO_VERDICTS), stats
