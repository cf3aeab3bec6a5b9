"""Keypoint refinement stage: the track-consistent NCC walk of the stored pairs, with the checks' verdicts
applied, over groups of whole tracks (resuming the groups the store holds)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..adapters.database import ColmapDatabase
from ..enums import Device
from ..recipe import Recipe
from .executor import Runner
from .read import ReadOutput, read_affines
from .store import GroupResult, RunStore, StoreDamaged
from .track_groups import DECODED_BY_IMAGE, group_max_matches, walk_groups
from .verdicts import NO_VERDICTS, Verdicts, output_matches


@dataclass(frozen=True)
class RefineKeypointsStats:
    """Counts of the keypoint refinement stage: the walk's counters summed over groups (empty when off) and the
    decodes per image over all processes."""

    counters: Mapping[str, float] = field(default_factory=dict)
    decoded_by_image: Mapping[int, int] = field(default_factory=dict)

    def count(self, key: str) -> int:
        """``counters[key]`` as an int (0 when absent)."""
        return int(self.counters.get(key, 0))


def run_refine_keypoints(db: ColmapDatabase, read: ReadOutput, store: RunStore, recipe: Recipe, device: str,
               runner: Runner, progress: bool, verdicts: Verdicts = NO_VERDICTS
               ) -> tuple[dict[int, np.ndarray], RefineKeypointsStats]:
    """The keypoint refinement stage on ``runner``, skipping and storing groups. Returns (image id -> new
    keypoints ``(N, 2)``, :class:`RefineKeypointsStats`); the read keypoints when off or nothing was
    filtered."""
    if not recipe.pipeline.refine_keypoints or not store.filter_counts().pairs_ok:
        return read.keypoints, RefineKeypointsStats()
    ok = verdicts.apply(store.load_filtered())
    missing = read.loader.missing
    usable = {k: v for k, v in ok.items() if k[0] not in missing and k[1] not in missing}
    ncfg = dataclasses.replace(recipe.ncc, device=Device(device)) if recipe.ncc.device == "auto" else recipe.ncc
    budget = recipe.pipeline.image_budget_bytes(runner.slots)
    # the groups are numbered for one image budget: stored groups of another are walked again
    done = store.refine_groups({"image_budget_bytes": budget, "group_max_matches": group_max_matches()},
                               read.loader.expected_sizes)
    new_keypoints, stats, used = walk_groups(
        read.loader, read.keypoints, usable, read_affines(db, read.keypoints), ncfg, recipe.tracks,
        unrefined={k: m for k, m in output_matches(db, ok, recipe.pipeline.source, verdicts).items()
                   if k not in usable},
        runner=runner,
        progress=progress, image_budget_bytes=budget, done=done, on_group=store.save_group,
        check_done=lambda n: check_resumed_groups(store, done, n))
    stats = dict(stats)
    decoded = {int(k): int(v) for k, v in stats.pop(DECODED_BY_IMAGE, {}).items()}
    # the images skipped before the walk count as missing too: the same number as images_missing
    counters = dict(stats, workers=used, missing_images=max(int(stats.get("missing_images", 0)), len(missing)))
    return new_keypoints, RefineKeypointsStats(counters=counters, decoded_by_image=decoded)


def check_resumed_groups(store: RunStore, done: Mapping[int, GroupResult], num_groups: int) -> None:
    """Refuse stored groups that are not groups of this run's plan (StoreDamaged naming the file)."""
    for g in sorted(done):
        if not 0 <= g < num_groups:
            raise StoreDamaged(store.group_path(g), f"group {g} is not one of this run's {num_groups} groups")
