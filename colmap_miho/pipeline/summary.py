"""What ``refine_database`` did: :class:`RefineSummary`, assembled from the stages' stats."""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from ..recipe import Recipe
from .filter import FilterStats
from .match_check_stage import MatchCheckStats
from .read import ReadStats
from .refine_keypoints import RefineKeypointsStats
from .write import WriteStats


@dataclass
class RefineSummary:
    """What ``refine_database`` did. Counters are over image pairs / matches / keypoints.

    Attributes:
        output: path of the written database.
        backup: timestamped copy of the input (``in_place`` only), else None.
        seed: the run's root seed (every stage's derives from it: :mod:`colmap_miho.seeds`).
        pairs_filtered: pairs with at least ``pipeline.min_matches`` matches, filtered.
        pairs_passed: pairs with fewer matches, left unchanged.
        pairs_failed: filtered pairs for which the filter found no plane; left unchanged.
        matches_in / matches_kept / matches_removed: over every pair of the source, in the
            input / in the output (after the filter's and the match check's
            removals) / their difference.
        keypoints_moved: keypoints whose position changed (each moves at most once).
        median_displacement_px / max_displacement_px: over the moved keypoints, pixels.
        images_missing: names of images that could not be read (not refined).
        images_implausible: names of images whose keypoints do not match their pixels (a file
            renamed or replaced after extraction; refined all the same, with a warning).
        runner: where the parallel work ran: "inline", "processes" or "dask".
        memory_budget_mb: ``pipeline.memory_budget_mb`` of the run.
        filter_chunks / filter_chunks_resumed: chunks of pairs filtered in all / taken from
            an interrupted run's store; pairs_resumed: the pairs of those chunks.
        refine_groups / refine_groups_resumed: track groups refined in all / taken from the
            store (0 when the keypoint refinement does not report groups).
        resumed: the run continued an interrupted one.
        image_decodes: image files decoded in the whole run, over all processes: the read
            stage's check (once per image; kept in the cache when it fits) and the track walk's
            (an image again in each worker whose groups need it and no longer cache it).
        image_decodes_max: the most times one image was decoded in the run (same count).
        match_check: what the match check against a global estimate of the cameras removed
            and why, whether the estimate was used and which images it trusted
            (:meth:`~.match_check_stage.MatchCheckStats.to_dict`; empty when it is off).
        seconds: wall time per stage ("copy", "read", "filter", "refine", "write", "verify",
            "total").
    """

    output: Path
    database: Path
    backup: Path | None = None
    recipe: str = ""
    seed: int = 0
    source: str = ""
    refined: bool = True
    verified: bool = False
    workers: int = 1
    device: str = "cpu"
    num_images: int = 0
    num_pairs: int = 0
    pairs_filtered: int = 0
    pairs_passed: int = 0
    pairs_failed: int = 0
    matches_in: int = 0
    matches_kept: int = 0
    matches_removed: int = 0
    keypoints_total: int = 0
    keypoints_moved: int = 0
    median_displacement_px: float = 0.0
    max_displacement_px: float = 0.0
    images_missing: list[str] = field(default_factory=list)
    images_implausible: list[str] = field(default_factory=list)
    runner: str = "inline"
    memory_budget_mb: int = 0
    filter_chunks: int = 0
    filter_chunks_resumed: int = 0
    pairs_resumed: int = 0
    refine_groups: int = 0
    refine_groups_resumed: int = 0
    resumed: bool = False
    image_decodes: int = 0
    image_decodes_max: int = 0
    refine_stats: dict = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    match_check: dict = field(default_factory=dict)

    @classmethod
    def from_stages(cls, *, output: Path, database: Path, backup: Path | None, recipe: Recipe,
                    device: str, seed: int, runner: str, resumed: bool, read: ReadStats, filtered: FilterStats,
                    refine: RefineKeypointsStats, write: WriteStats, seconds: dict[str, float],
                    match_check: MatchCheckStats | None = None) -> RefineSummary:
        """Assemble the summary from the stages' stats (a check's None: it was off)."""
        pcfg = recipe.pipeline
        per_image = Counter(read.decoded_by_image)
        per_image.update(refine.decoded_by_image)
        return cls(
            output=output, database=database, backup=backup, recipe=recipe.name, seed=int(seed),
            source=str(pcfg.source), refined=pcfg.refine_keypoints, verified=pcfg.verify,
            workers=filtered.workers, device=device, num_images=read.num_images,
            num_pairs=read.num_pairs, pairs_filtered=filtered.pairs_filtered,
            pairs_passed=read.pairs_passed, pairs_failed=filtered.pairs_failed,
            matches_in=read.matches_in, matches_kept=write.matches_kept,
            matches_removed=read.matches_in - write.matches_kept, keypoints_total=read.keypoints_total,
            keypoints_moved=write.keypoints_moved,
            median_displacement_px=write.median_displacement_px,
            max_displacement_px=write.max_displacement_px,
            images_missing=list(read.images_missing), images_implausible=list(read.images_implausible),
            runner=runner, memory_budget_mb=pcfg.memory_budget_mb,
            filter_chunks=filtered.chunks, filter_chunks_resumed=filtered.chunks_resumed,
            pairs_resumed=filtered.pairs_resumed, refine_groups=refine.count("groups"),
            refine_groups_resumed=refine.count("groups_resumed"), resumed=resumed,
            image_decodes=read.image_decodes + refine.count("image_decodes"),
            image_decodes_max=max(per_image.values(), default=0),
            refine_stats=dict(refine.counters), seconds=seconds,
            match_check={} if match_check is None else match_check.to_dict())

    def to_dict(self) -> dict:
        """Plain JSON-ready data (paths as strings, seconds rounded to ms)."""
        out = dataclasses.asdict(self)
        for key in ("output", "database", "backup"):
            out[key] = None if out[key] is None else str(out[key])
        out["seconds"] = {k: round(v, 3) for k, v in self.seconds.items()}
        return out

    def format(self) -> str:
        """A one-screen human summary."""
        kept_pct = 100.0 * self.matches_kept / self.matches_in if self.matches_in else 0.0
        lines = [
            f"colmap-miho refine: {self.database} -> {self.output}",
            f"  recipe {self.recipe}, source {self.source}, refine {'on' if self.refined else 'off'}, "
            f"verify {'on' if self.verified else 'off'}, {self.workers} worker(s) ({self.runner}), {self.device}",
            f"  images {self.num_images}, pairs {self.num_pairs}: {self.pairs_filtered} filtered, "
            f"{self.pairs_passed} too small (unchanged), {self.pairs_failed} no plane found (unchanged)",
            f"  matches {self.matches_in} -> kept {self.matches_kept} ({kept_pct:.1f}%), "
            f"removed {self.matches_removed}",
            f"  keypoints moved {self.keypoints_moved} of {self.keypoints_total}, median displacement "
            f"{self.median_displacement_px:.2f} px, max {self.max_displacement_px:.2f} px",
        ]
        if self.resumed:
            lines.append(f"  resumed: {self.filter_chunks_resumed} of {self.filter_chunks} filter chunks "
                         f"({self.pairs_resumed} pairs) and {self.refine_groups_resumed} of "
                         f"{self.refine_groups} refine groups were finished before")
        if self.match_check:
            from ..reporting.html_report import match_check_note

            lines.append(match_check_note(self.match_check, label="  match check", timing=True, sep="\n    "))
        if self.images_missing:
            lines.append(f"  images not refined (missing/unreadable): {', '.join(self.images_missing)}")
        if self.images_implausible:
            lines.append(f"  images whose keypoints do not match their pixels: {', '.join(self.images_implausible)}")
        if self.backup:
            lines.append(f"  backup of the input: {self.backup}")
        lines.append("  seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in self.seconds.items()))
        return "\n".join(lines)
