"""The track walk of the keypoint refinement over groups of whole tracks that fit the image budget, walked
here or on the runner's slots; results do not depend on either (tracks never share a keypoint)."""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, Future, wait

import numpy as np

from ..adapters.images import ImageLoader
from ..enums import RunnerKind
from ..errors import InvalidInput
from .executor import Runner

#: Refinement runs in worker processes only with at least this many refinable matches each.
MIN_MATCHES_PER_REFINE_WORKER = 2000

#: When the filter stage did not start the process pool, refinement starts it only with at
#: least this many refinable matches per worker: a worker's first group waits for the
#: forkserver's imports if they have not finished, which only a large enough share of the walk
#: pays back. Dask clusters are started already.
MIN_MATCHES_TO_START_WORKERS = 10_000

#: Most refinable matches of one group of tracks, in units of
#: :data:`MIN_MATCHES_PER_REFINE_WORKER`: a group is the unit of work handed to a worker and
#: of what a resumed run keeps (a fixed number, so the groups do not depend on the runner).
GROUP_SIZE_IN_WORKER_MINIMUMS = 10


def group_max_matches() -> int:
    """Most refinable matches of one group (part of a resumed run's plan key)."""
    return GROUP_SIZE_IN_WORKER_MINIMUMS * MIN_MATCHES_PER_REFINE_WORKER

#: Key of the keypoint refinement's stats holding image id -> decodes by the walk (all processes).
DECODED_BY_IMAGE = "decoded_by_image"

#: (image id, keypoint indices (K,) int64, new positions (K, 2) float64) per image of a group.
Moved = dict[int, tuple[np.ndarray, np.ndarray]]

#: The loader of this worker process, kept from one task to the next (image reuse).
_WORKER_LOADER: ImageLoader | None = None


def _import_plan():
    """The track plan, imported only when a run refines (so a worker that walks never imports torch here)."""
    from ..refinement.tracks.build import build_track_plan, local_affine_of

    return build_track_plan, local_affine_of


def _walk_counters() -> tuple[str, ...]:
    from ..refinement.lsm.step import LSM_COUNTERS
    from ..refinement.tracks.multiphoto import MULTIPHOTO_COUNTERS
    from ..refinement.tracks.walk import WALK_COUNTERS

    return (WALK_COUNTERS + LSM_COUNTERS + MULTIPHOTO_COUNTERS
            + ("missing_images", "images_loaded", "image_decodes", "seconds"))


def max_images_for(loader: ImageLoader, image_ids, budget_bytes: int | None,
                   fallback: int) -> int:
    """Images a group may use (at least 2): as many of the largest as fit ``budget_bytes`` and the
    loader's bounds; ``fallback`` when no bound is known."""
    sizes = [b for b in (loader.image_bytes(i) for i in image_ids) if b]
    bounds = [loader.max_cached] if loader.max_cached is not None else []
    for budget in (budget_bytes, loader.max_cached_bytes):
        if budget is not None and sizes:
            bounds.append(int(budget) // max(sizes))
    return max(2, min(bounds) if bounds else int(fallback))


def _moved_of(group, keypoints) -> Moved:
    out: Moved = {}
    for i, arr in keypoints.items():
        arr = np.asarray(arr, np.float64)
        idx = np.flatnonzero(np.any(arr != group.keypoints[i], axis=1))
        if idx.size:
            out[int(i)] = (idx.astype(np.int64), arr[idx].copy())
    return out


def _walk_group(loader, group, ncc_config, track_config, affines, on_progress=None):
    """Walk one group; returns (moved, stats) with its counters and ``decoded_by_image``."""
    from ..refinement.tracks.walk import walk_tracks

    before = Counter(loader.decoded)
    tr = walk_tracks(loader, group, ncc_config=ncc_config, track_config=track_config,
                     affines=affines, progress=False, on_progress=on_progress)
    numeric = _numeric(tr.stats)
    stats: dict = {k: numeric[k] for k in _walk_counters() if k in numeric}
    stats[DECODED_BY_IMAGE] = {str(k): int(v) for k, v in (loader.decoded - before).items()}
    return _moved_of(group, tr.keypoints), stats


def _walk_group_task(loader_state: dict, group, ncc_config, track_config, affines):
    """Worker task: walk one group with this process's loader, kept with its cache for the next group."""
    global _WORKER_LOADER
    state = dict(loader_state)
    names, sizes = state.pop("names"), state.pop("expected_sizes")
    loader = _WORKER_LOADER
    if loader is None or {k: getattr(loader, k) for k in state} != state:
        loader = _WORKER_LOADER = ImageLoader(names=names, expected_sizes=sizes, **state)
    else:
        loader.add_images(names, sizes)
    return _walk_group(loader, group, ncc_config, track_config, affines)


def _group_args(loader: ImageLoader, group, affines, budget_bytes: int | None
                ) -> tuple[dict, Mapping | None]:
    """What a worker needs besides the group: loader settings for its images and their affine frames."""
    ids = group.image_ids
    state = dict(loader.state(), max_cached_bytes=budget_bytes or loader.max_cached_bytes)
    state["names"] = {i: loader.names[i] for i in ids}
    state["expected_sizes"] = {i: loader.expected_sizes[i] for i in ids
                               if i in loader.expected_sizes}
    aff = None if affines is None else {i: affines[i] for i in ids if i in affines}
    return state, aff


def _merge_walk_stats(plan_stats: dict, parts: list[dict]) -> dict:
    """The plan's stats with the groups' counters summed (``levels``, ``missing_images``: the largest)."""
    stats = dict(plan_stats)
    keys = dict.fromkeys(k for st in parts for k in st if k != DECODED_BY_IMAGE)
    for key in keys:
        vals = [st[key] for st in parts if key in st]
        if vals:
            stats[key] = max(vals) if key in ("levels", "missing_images") else sum(vals)
    decoded: Counter[int] = Counter()
    for st in parts:
        decoded.update({int(k): int(v) for k, v in st.get(DECODED_BY_IMAGE, {}).items()})
    return {**_numeric(stats), DECODED_BY_IMAGE: dict(decoded)}


def _runs(groups: list, n: int) -> list[list[int]]:
    work = np.cumsum([g.to_refine for g in groups], dtype=np.float64)
    cut = np.searchsorted(work, work[-1] * np.arange(1, n) / n, side="right")
    bounds = [0, *sorted(set(cut.tolist())), len(groups)]
    return [list(range(a, b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def walk_groups(loader: ImageLoader, keypoints, pairs, affines, ncc_config, track_config, *,
                     unrefined=None, runner: Runner, progress: bool = False,
                     image_budget_bytes: int | None = None,
                     done: Mapping[int, tuple[Moved, dict]] | None = None,
                     on_group: Callable[[int, Moved, dict], None] | None = None,
                     check_done: Callable[[int], None] | None = None):
    """The track-consistent NCC walk over groups of whole tracks, on ``runner``.

    ``pairs``: (i, j) -> (matches ``(M, 2)``, FilterResult); ``unrefined``: other output matches
    (join tracks, never refine); ``done``: groups finished by an earlier run; ``on_group`` is called
    as each group finishes. Returns (new keypoints, stats, processes used)."""
    build_track_plan, local_affine_of = _import_plan()
    plan = build_track_plan(keypoints, {k: m for k, (m, _) in pairs.items()},
                            {k: r for k, (_, r) in pairs.items()}, unrefined_matches=unrefined,
                            duplicate_px=track_config.duplicate_px,
                            local_affine=local_affine_of(ncc_config))
    n_edges = int(plan.refinable().sum())
    if not n_edges:
        return keypoints, _numeric(plan.stats), 1
    max_images = max_images_for(loader, plan.image_ids, image_budget_bytes,
                                track_config.max_images_in_memory)
    groups = plan.groups(max_images, group_max_matches())
    done = dict(done or {})
    if check_done is not None:
        check_done(len(groups))
    if any(not 0 <= g < len(groups) for g in done):
        raise InvalidInput(f"resumed group indices must be in 0..{len(groups) - 1} (were the "
                         "inputs or the image budget changed since?)")
    new = {i: np.array(keypoints[i], np.float64) for i in keypoints}
    group_stats: list[dict] = []
    attach = _LocalPairs(plan, groups, skip=done)

    def finish(g: int, moved: Moved, st: dict, *, resumed: bool = False) -> None:
        for i, (idx, xy) in moved.items():
            new[i][idx] = xy
        group_stats.append(st)
        if not resumed and on_group is not None:
            on_group(g, moved, st)

    todo = [g for g in range(len(groups)) if g not in done]
    for g in sorted(done):
        finish(g, *done[g], resumed=True)
    use = 1
    if runner.parallel and (runner.started or runner.kind == RunnerKind.DASK
                            or n_edges >= MIN_MATCHES_TO_START_WORKERS * runner.slots):
        use = min(runner.slots, max(1, n_edges // MIN_MATCHES_PER_REFINE_WORKER), max(1, len(todo)))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=plan.to_refine, desc="NCC tracks" + (f" ({use} workers)" if use > 1 else ""),
                   unit="kp", initial=sum(groups[g].to_refine for g in done))
    try:
        if use <= 1:
            with _torch_threads(1 if ncc_config.device != "cuda" else None):
                for g in todo:
                    finish(g, *_walk_group(loader, attach(g), ncc_config, track_config, affines,
                                           bar.update if bar is not None else None))
        else:
            loader.clear_cache()  # the workers' loaders hold the images from here on
            _dispatch(runner, loader, groups, todo, use, attach,
                      (ncc_config, track_config, affines, image_budget_bytes), finish, bar)
    finally:
        if bar is not None:
            bar.close()
    stats = _merge_walk_stats(plan.stats, group_stats)
    stats.update(groups=len(groups), groups_resumed=len(done), group_max_images=max_images)
    return new, stats, use


class _LocalPairs:
    """``attach(g)``: group ``g`` with its local affine pairs, fitted at first use and forgotten
    after the last; ``attach.inputs(g)`` lets the worker fit them instead (the same bits)."""

    def __init__(self, plan, groups: list, skip) -> None:
        self.plan, self.groups = plan, groups
        self.left: dict[int, int] = {}
        for g, grp in enumerate(groups):
            if g not in skip:
                for p in grp.source_pairs.tolist():
                    self.left[p] = self.left.get(p, 0) + 1

    def __call__(self, g: int):
        grp = self.plan.attach_local(self.groups[g])
        for p in self.groups[g].source_pairs.tolist():
            self.left[p] -= 1
            if not self.left[p]:
                self.plan.release_local([p])
        return grp

    def inputs(self, g: int):
        return self.plan.with_local_inputs(self.groups[g])


def _dispatch(runner, loader, groups, todo, use, attach, args, finish, bar) -> None:
    """Walk the ``todo`` groups: ``use`` contiguous runs, one group of each in flight, the next
    handed out as soon as the last returns; an idle slot takes the last group of the run with the
    most keypoints left. Where a group is walked does not change its result."""
    ncc_config, track_config, affines, budget = args
    runs = [[todo[k] for k in r] for r in _runs([groups[g] for g in todo], use)]
    pending: dict[Future, tuple[int, int]] = {}
    ready: dict[int, tuple] = {}  # run -> the task arguments of its next group

    def prepare(r: int) -> None:
        if runs[r] and r not in ready:
            g = runs[r][0]
            state, aff = _group_args(loader, groups[g], affines, budget)
            ready[r] = (state, attach.inputs(g), ncc_config, track_config, aff)

    def steal(r: int) -> None:
        left = [sum(groups[g].to_refine for g in run) if run else -1 for run in runs]
        d = int(np.argmax(left))
        if left[d] < 0:
            return
        runs[r].append(runs[d].pop())
        if not runs[d] and d in ready:  # the group taken was the one prepared
            ready[r] = ready.pop(d)

    def submit(r: int) -> None:
        if not runs[r]:
            steal(r)
        if runs[r]:
            prepare(r)
            g = runs[r].pop(0)
            pending[runner.submit(_walk_group_task, *ready.pop(r))] = (r, g)

    for r in range(len(runs)):
        submit(r)
    for r in range(len(runs)):
        prepare(r)
    while pending:
        finished, _ = wait(list(pending), return_when=FIRST_COMPLETED)
        done = []
        for fut in sorted(finished, key=lambda f: pending[f][1]):
            r, g = pending.pop(fut)
            done.append((g, *fut.result()))  # a failed group stops the run now
            submit(r)
        for g, moved, st in done:
            finish(g, moved, st)
            if bar is not None:
                bar.update(groups[g].to_refine)
        for r in range(len(runs)):
            prepare(r)


@contextlib.contextmanager
def _torch_threads(n: int | None):
    """Run a block with ``n`` torch intra-op threads, then restore the caller's setting."""
    if n is None:
        yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _numeric(stats: dict) -> dict:
    return {k: v for k, v in stats.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
