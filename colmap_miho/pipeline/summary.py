"""What ``refine_database`` did: :class:`RefineSummary`, assembled from the stages' stats."""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from ..recipe import Recipe
from .filter import FilterStats
from .match_check import MatchCheckStats
from .pair_check import PairCheckStats
from .read import ReadStats
from .refine import RefineStats
from .write import WriteStats


@dataclass
class RefineSummary:
    """What ``refine_database`` did; counters are over image pairs, matches or keypoints.

    Attributes:
        output / backup: the written database / the input's timestamped copy (``in_place`` only).
        pairs_filtered / pairs_passed / pairs_failed: pairs filtered / too small, left unchanged /
          with no plane found, left unchanged.
        matches_in / matches_kept / matches_removed: over every pair, after filter and checks.
        keypoints_moved, median_displacement_px, max_displacement_px: keypoints moved (each at most
          once) and how far, in pixels.
        images_missing / images_implausible: images not read / whose keypoints do not fit their pixels.
        image_decodes / image_decodes_max: image files decoded over all processes / most of one image.
        pair_check / match_check: what each check removed and why (empty when off).
        seconds: wall time per stage.
    """

    output: Path
    database: Path
    backup: Path | None = None
    recipe: str = ""
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
    pair_check: dict = field(default_factory=dict)
    match_check: dict = field(default_factory=dict)

    @classmethod
    def from_stages(cls, *, output: Path, database: Path, backup: Path | None, recipe: Recipe,
                    device: str, runner: str, resumed: bool, read: ReadStats, filtered: FilterStats,
                    refine: RefineStats, write: WriteStats, seconds: dict[str, float],
                    pair_check: PairCheckStats | None = None,
                    match_check: MatchCheckStats | None = None) -> RefineSummary:
        """Assemble the summary from the stages' stats (a check's None: it was off)."""
        pcfg = recipe.pipeline
        per_image = Counter(read.decoded_by_image)
        per_image.update(refine.decoded_by_image)
        return cls(
            output=output, database=database, backup=backup, recipe=recipe.name,
            source=str(pcfg.source), refined=pcfg.refine, verified=pcfg.verify,
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
            pair_check={} if pair_check is None else pair_check.to_dict(),
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
        if self.pair_check:
            lines.append(_pair_check_line(self.pair_check))
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


def _pair_check_line(pc: dict) -> str:
    done = f"{pc['pairs_removed']} removed" if pc["mode"] == "remove" else f"{pc['pairs_flagged']} flagged"
    line = (f"  pair check: {pc['pairs_checked']} pairs, {pc['triangles']} triangles "
            f"({pc['triangles_broken']} broken), {done}")
    line += "".join(f"\n    {' - '.join(w['images'])}: {w['reason']}" for w in pc["wrong_pairs"][:10])
    if len(pc["wrong_pairs"]) > 10:
        line += f"\n    ... and {len(pc['wrong_pairs']) - 10} more (see the JSON report)"
    return line
