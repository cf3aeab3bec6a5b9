"""Filter stage: MOP / MOP+MiHo on every pair with enough matches, in chunks stored in the run
store. Results do not depend on chunking, workers or engine: each pair's seed comes from its image
ids."""

from __future__ import annotations

import math
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..adapters.database import ColmapDatabase, PairRecord
from ..enums import MatchSource, RunnerKind
from ..filtering.api import filter_matches
from ..filtering.config import FilterConfig
from ..seeds import pair_seed
from .read import check_match_indices
from .records import PairOutcome

if TYPE_CHECKING:
    from .executor import Runner
    from .store import RunStore

#: Below this many pairs to filter per parallel slot, filtering runs in this process (handing
#: work to a worker costs its pickled inputs and, early in a run, the wait for the
#: forkserver's imports). Dask runs always use the cluster (it is started already).
MIN_PAIRS_PER_WORKER = 4

#: Below this many matches to filter per parallel slot, filtering runs in this process too:
#: workers need the forkserver's imports (overlapping the parent's setup) and their inputs
#: pickled, which a small amount of filtering does not pay back.
MIN_MATCHES_PER_FILTER_WORKER = 10_000

#: Bytes this process holds per match of a chunk in flight: positions (2 x 2 float64), indices
#: (2 uint32), the result's flag and label, and their pickled copies; an upper estimate that
#: sizes the chunks from the memory budget.
BYTES_PER_MATCH_IN_FLIGHT = 160

#: Share of ``pipeline.memory_budget_mb`` for the chunks in flight (the stage runs alone: the
#: rest covers the filter's own working arrays, up to 2048 hypotheses x N matches per task).
FILTER_BUDGET_SHARE = 0.25

#: Most matches in one chunk whatever the budget: a chunk is the unit a resumed run skips
#: (about a minute of one core's work at most).
MAX_CHUNK_MATCHES = 200_000

#: A parallel run cuts its pairs into at least this many chunks per slot (load balance).
CHUNKS_PER_SLOT = 4

#: Chunks read ahead per parallel slot (one running, one queued).
IN_FLIGHT_PER_SLOT = 2


@dataclass(frozen=True, kw_only=True)
class FilterOptions:
    """Run options of the filter stage.

    Attributes:
        source: which matches are read (``pipeline.source``).
        seed: base seed; each pair's seed is :func:`~colmap_miho.seeds.pair_seed` of it and the ids.
        memory_budget_bytes: ``pipeline.memory_budget_mb`` in bytes (sizes the chunks).
        device: "cpu" (the numpy filter) or "cuda" (the torch filter on the GPU, in this process).
        progress: tqdm bar over pairs.
        database_name: the user's database, named in error messages (the stage reads a copy).
    """

    source: MatchSource
    memory_budget_bytes: int
    seed: int = 0
    device: str = "cpu"
    progress: bool = False
    database_name: str = ""


@dataclass(frozen=True, kw_only=True)
class FilterStats:
    """Counts of the filter stage (``RefineSummary`` fields), matches over the successful pairs."""

    workers: int
    pairs_filtered: int
    pairs_failed: int
    matches_in: int
    matches_kept: int
    chunks: int = 0
    chunks_resumed: int = 0
    pairs_resumed: int = 0

    @property
    def matches_removed(self) -> int:
        return self.matches_in - self.matches_kept


def chunk_matches(budget_bytes: int, slots: int, total_matches: int) -> int:
    """Most matches per chunk: the budget's share over the chunks in flight, bounded by
    :data:`MAX_CHUNK_MATCHES` and :data:`CHUNKS_PER_SLOT`."""
    cap = budget_bytes * FILTER_BUDGET_SHARE / (IN_FLIGHT_PER_SLOT * max(1, slots) * BYTES_PER_MATCH_IN_FLIGHT)
    cap = min(cap, MAX_CHUNK_MATCHES)
    if slots > 1:
        cap = min(cap, math.ceil(total_matches / (CHUNKS_PER_SLOT * slots)))
    return max(1, int(cap))


def plan_chunks(pairs: list[PairRecord], max_matches: int) -> list[list[PairRecord]]:
    """Cut ``pairs`` in order into runs of at most ``max_matches`` matches (a larger pair alone)."""
    chunks: list[list[PairRecord]] = []
    current: list[PairRecord] = []
    size = 0
    for p in pairs:
        if current and size + p.num_matches > max_matches:
            chunks.append(current)
            current, size = [], 0
        current.append(p)
        size += p.num_matches
    if current:
        chunks.append(current)
    return chunks


def filter_chunk(items: list[tuple[np.ndarray, np.ndarray, int]], cfg: FilterConfig,
                 device: str = "cpu") -> list[PairOutcome]:
    """Task: filter ``items`` = ``[(pts1 (M, 2), pts2 (M, 2), seed), ...]`` on ``device``."""
    return [PairOutcome.of(filter_matches(p1, p2, method=cfg.method, config=cfg, seed=s, device=device))
            for p1, p2, s in items]


def run_filter(db: ColmapDatabase, pairs: list[PairRecord], keypoints: dict[int, np.ndarray],
               cfg: FilterConfig, opts: FilterOptions, *, runner: Runner, store: RunStore) -> FilterStats:
    """Filter ``pairs`` chunk by chunk into ``store``, skipping stored ones; returns the counts over
    all pairs. DatabaseError for matches past an image's keypoints; StoreDamaged for a foreign
    chunk."""
    store.expect(((p.image_id1, p.image_id2) for p in pairs), {i: len(k) for i, k in keypoints.items()})
    done = store.filtered_pairs()
    todo = [p for p in pairs if (p.image_id1, p.image_id2) not in done]
    resumed = store.filter_counts()
    todo_matches = sum(p.num_matches for p in todo)
    parallel = runner.parallel and (runner.kind == RunnerKind.DASK or (
        len(todo) >= MIN_PAIRS_PER_WORKER * runner.slots
        and todo_matches >= MIN_MATCHES_PER_FILTER_WORKER * runner.slots))
    slots = runner.slots if parallel else 1
    chunks = plan_chunks(todo, chunk_matches(opts.memory_budget_bytes, slots, todo_matches))
    _filter_chunks(db, chunks, keypoints, cfg, opts, runner if parallel else None, store)
    total = store.filter_counts()
    return FilterStats(workers=slots, pairs_filtered=total.pairs, pairs_failed=total.pairs - total.pairs_ok,
                       matches_in=total.matches_in, matches_kept=total.matches_kept, chunks=total.chunks,
                       chunks_resumed=resumed.chunks, pairs_resumed=resumed.pairs)


def _filter_chunks(db: ColmapDatabase, chunks: list[list[PairRecord]], keypoints, cfg: FilterConfig,
                   opts: FilterOptions, runner: Runner | None, store: RunStore) -> None:
    """Filter ``chunks`` here or on ``runner``, reading ahead at most :data:`IN_FLIGHT_PER_SLOT` per
    slot; this process filters too while a new pool starts."""
    first = store.next_filter_index()
    bar = None
    if opts.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(len(c) for c in chunks), desc="filter pairs", unit="pair")

    def read(chunk: list[PairRecord]):
        matches, items = [], []
        for p in chunk:
            i, j = p.image_id1, p.image_id2
            m = db.matches(i, j, opts.source)
            check_match_indices(m, len(keypoints[i]), len(keypoints[j]), (i, j), opts.database_name)
            matches.append(m)
            items.append((keypoints[i][m[:, 0]], keypoints[j][m[:, 1]], pair_seed(opts.seed, i, j)))
        return matches, items

    def finish(index: int, chunk: list[PairRecord], matches: list[np.ndarray], outcomes: list[PairOutcome]):
        store.save_filter_chunk(index, [(p.image_id1, p.image_id2) for p in chunk], matches, outcomes)
        if bar:
            bar.update(len(chunk))

    try:
        if runner is None:
            for k, chunk in enumerate(chunks):
                matches, items = read(chunk)
                finish(first + k, chunk, matches, filter_chunk(items, cfg, opts.device))
            return
        pending: dict[Future, tuple[int, list[PairRecord], list[np.ndarray]]] = {}

        def collect(futs) -> None:
            for fut in futs:
                finish(*pending.pop(fut), fut.result())

        todo = deque(enumerate(chunks))
        # A process pool that is not running yet needs its forkserver's imports (numpy, torch):
        # meanwhile this process filters chunks itself.
        starting = runner.start_in_background() if runner.kind == RunnerKind.PROCESSES else (lambda: False)
        while todo and starting():
            k, chunk = todo.popleft()
            matches, items = read(chunk)
            finish(first + k, chunk, matches, filter_chunk(items, cfg, opts.device))
        for k, chunk in todo:
            matches, items = read(chunk)
            pending[runner.submit(filter_chunk, items, cfg, opts.device)] = (first + k, chunk, matches)
            if len(pending) >= IN_FLIGHT_PER_SLOT * runner.slots:
                collect(wait(list(pending), return_when=FIRST_COMPLETED).done)
        while pending:
            collect(wait(list(pending), return_when=FIRST_COMPLETED).done)
    finally:
        if bar:
            bar.close()
