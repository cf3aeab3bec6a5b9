"""Filter stage: MOP / MOP+MiHo on every pair with enough matches, in this process or in
``spawn``-ed worker processes (one thread each), streaming the matches from the database.

Results do not depend on the worker count: each pair's seed is derived from its image ids.
"""

from __future__ import annotations

from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass

import numpy as np

from ..adapters.database import ColmapDatabase, PairRecord
from ..enums import MatchSource
from ..filtering.api import FilterResult, filter_matches
from ..filtering.config import FilterConfig
from .read import check_match_indices
from .workers import init_worker, pair_seed, process_pool, single_thread_children

#: Below this many pairs to filter per worker, filtering runs in this process (starting a
#: worker process costs seconds: it imports torch).
MIN_PAIRS_PER_WORKER = 4

#: (image_id1, image_id2) -> (matches uint32 ``(M, 2)`` keypoint indices, the pair's result)
FilteredPairs = dict[tuple[int, int], tuple[np.ndarray, FilterResult]]


@dataclass(frozen=True, kw_only=True)
class FilterOptions:
    """Run options of the filter stage.

    Attributes:
        source: which matches are read (``pipeline.source``).
        seed: base seed; each pair's seed is :func:`~.workers.pair_seed` of it and the ids.
        workers: processes available (fewer are used for small jobs).
        progress: tqdm bar over pairs.
        database_name: the user's database, named in error messages (the stage reads a copy).
    """

    source: MatchSource
    seed: int = 0
    workers: int = 1
    progress: bool = False
    database_name: str = ""


@dataclass(frozen=True, kw_only=True)
class FilterStats:
    """Counts of the filter stage (``RefineSummary`` fields of the same names); matches are
    counted over the pairs where the filter succeeded."""

    workers: int
    pairs_filtered: int
    pairs_failed: int
    matches_in: int
    matches_kept: int

    @property
    def matches_removed(self) -> int:
        return self.matches_in - self.matches_kept


def run_filter(db: ColmapDatabase, pairs: list[PairRecord], keypoints: dict[int, np.ndarray],
               cfg: FilterConfig, opts: FilterOptions) -> tuple[FilteredPairs, FilterStats]:
    """Filter ``pairs`` (their matches read from ``db``, positions from ``keypoints``).

    Returns:
        ``(ok, stats)``: ``ok`` holds the pairs where a plane was found (failed pairs are
        left unchanged by the pipeline and only counted).
    """
    workers = opts.workers if len(pairs) >= MIN_PAIRS_PER_WORKER * opts.workers else 1
    filtered = _filter_pairs(db, pairs, keypoints, cfg, opts, workers)
    ok = {k: v for k, v in filtered.items() if bool(v[1].success)}
    stats = FilterStats(
        workers=workers, pairs_filtered=len(filtered), pairs_failed=len(filtered) - len(ok),
        matches_in=int(sum(len(m) for m, _ in ok.values())),
        matches_kept=int(sum(int(np.count_nonzero(r.inliers)) for _, r in ok.values())))
    return ok, stats


def _filter_one(i: int, j: int, pts1: np.ndarray, pts2: np.ndarray, cfg: FilterConfig, seed: int):
    """Run the filter on one pair (in a worker or in-process); returns (i, j, result)."""
    return i, j, filter_matches(pts1, pts2, method=cfg.method, config=cfg, seed=seed)


def _filter_pairs(db: ColmapDatabase, pairs: list[PairRecord], keypoints, cfg: FilterConfig,
                  opts: FilterOptions, workers: int) -> FilteredPairs:
    """Filter every pair, streaming matches from the database into a bounded worker queue."""
    results: FilteredPairs = {}
    matches_of: dict[tuple[int, int], np.ndarray] = {}
    bar = None
    if opts.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(pairs), desc="filter pairs", unit="pair")

    def job(p: PairRecord):
        i, j = p.image_id1, p.image_id2
        m = db.matches(i, j, opts.source)
        check_match_indices(m, len(keypoints[i]), len(keypoints[j]), (i, j), opts.database_name)
        matches_of[(i, j)] = m
        return i, j, keypoints[i][m[:, 0]], keypoints[j][m[:, 1]], cfg, pair_seed(opts.seed, i, j)

    def collect(i: int, j: int, res: FilterResult) -> None:
        results[(i, j)] = (matches_of.pop((i, j)), res)
        if bar:
            bar.update()

    try:
        if workers <= 1:
            for p in pairs:
                collect(*_filter_one(*job(p)))
            return results
        with single_thread_children(), process_pool(workers, initializer=init_worker) as ex:
            pending = set()
            for p in pairs:
                pending.add(ex.submit(_filter_one, *job(p)))
                if len(pending) >= 2 * workers:  # bounded: stream pairs, do not queue all
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        collect(*fut.result())
            for fut in pending:
                collect(*fut.result())
    finally:
        if bar:
            bar.close()
    return results
