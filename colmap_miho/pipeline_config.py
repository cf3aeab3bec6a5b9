"""Configuration of the database pipeline (``colmap-miho refine``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .enums import MatchSource
from .validation import MAX_MATCHES, MAX_MEMORY_BUDGET_MB, check_bounds, within
from .validation import MIN_MEMORY_BUDGET_MB as MIN_MEMORY_BUDGET_MB

#: ``pipeline.memory_budget_mb`` default (MiB).
DEFAULT_MEMORY_BUDGET_MB = 2048
#: Share of the memory budget for decoded images in the keypoint refinement (the rest: the track
#: plan, the NCC batches and the filter results the stage reads back).
IMAGE_BUDGET_SHARE = 0.5


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    """Parameters of ``colmap-miho refine``.

    Attributes:
        source: which matches are filtered: "verified" (two_view_geometries inliers) or "raw"
            (tentative matches; MOP+MiHo then replaces geometric verification).
        min_matches: pairs with fewer matches pass through unchanged.
        refine_keypoints: move the kept keypoints by the track-consistent refinement after
            filtering (false: filter only, ``refine --no-refine``).
        verify: re-run COLMAP's epipolar verification on the kept matches.
        memory_budget_mb: MiB for the filter's chunks of pairs and (half of it) the keypoint
            refinement's decoded images; results do not depend on it. The keypoints and the
            filtered matches (about 40 bytes each) are held outside it.
    """

    source: MatchSource = MatchSource.VERIFIED
    min_matches: int = field(default=15, metadata=within(
        4, MAX_MATCHES, "a homography needs 4 matches; no pair holds more"))
    refine_keypoints: bool = True
    verify: bool = False
    memory_budget_mb: int = field(default=DEFAULT_MEMORY_BUDGET_MB, metadata=within(
        MIN_MEMORY_BUDGET_MB, MAX_MEMORY_BUDGET_MB, "MiB; at least one chunk, at most 1 TiB"))

    def __post_init__(self) -> None:
        object.__setattr__(self, "source", MatchSource.parse(self.source, "source"))
        check_bounds(self)

    @property
    def memory_budget_bytes(self) -> int:
        """``memory_budget_mb`` in bytes."""
        return int(self.memory_budget_mb) * 2**20

    def image_budget_bytes(self, slots: int) -> int:
        """Decoded image bytes one of ``slots`` parallel refine tasks may hold."""
        return int(self.memory_budget_bytes * IMAGE_BUDGET_SHARE) // max(1, int(slots))
