"""Configuration of the database pipeline (``colmap-miho refine``)."""

from __future__ import annotations

from dataclasses import dataclass

from ..enums import MatchSource


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    """Parameters of ``colmap-miho refine``.

    Attributes:
        source: which matches are filtered: "verified" (two_view_geometries inliers)
            or "raw" (tentative matches; MOP+MiHo then replaces geometric verification).
        min_matches: pairs with fewer matches pass through unchanged.
        refine: run the track-consistent NCC refinement after filtering.
        verify: re-run COLMAP's epipolar verification on the kept matches.
    """

    source: MatchSource = MatchSource.VERIFIED
    min_matches: int = 15
    refine: bool = True
    verify: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "source", MatchSource.parse(self.source, "source"))
        if self.min_matches < 4:
            raise ValueError(f"min_matches must be >= 4, got {self.min_matches}")
