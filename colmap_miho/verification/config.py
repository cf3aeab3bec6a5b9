"""Configuration of the match check (a pure dataclass, no I/O)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from ..enums import MatchCheckMode
from ..validation import MAX_THRESHOLD_PX, PX, check_bounds, within


@dataclass(frozen=True, kw_only=True)
class MatchCheckConfig:
    """The match check: every match judged against a global estimate of the cameras (how it
    works: ``docs/how-it-works.md``; its figures: ``docs/results.md``, the match check).

    Attributes:
        mode: "remove" the matches a trusted estimate contradicts, "flag" them only, or "off".
        false_reject: share of correct matches the threshold would remove were their distances
            exactly exponential (0.0027: a normal's 3-sigma tail).
        min_threshold_px / max_threshold_px: bounds of that threshold, pixels.
        estimate_matches_per_image: the estimate is built from whole tracks sampled to about
            this many match ends per image (0: every match); bounds the mapper's cost.
        max_rounds: global estimates at most; a later one re-estimates the images not trusted yet.

    The class constants below are the check's fixed rules, not recipe keys.
    """

    mode: MatchCheckMode = MatchCheckMode.REMOVE
    false_reject: float = field(default=0.0027, metadata=within(
        0, 0.5, "a probability in the tail of the residuals", lo_open=True, hi_open=True))
    min_threshold_px: float = field(default=2.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    max_threshold_px: float = field(default=4.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    estimate_matches_per_image: int = field(default=2000, metadata=within(
        0, 1_000_000_000, "match ends of an image (0: all)"))
    max_rounds: int = field(default=2, metadata=within(1, 5, "global-mapper runs"))

    #: degrees: a pair agrees with the estimate when its own relative rotation is this close.
    max_rotation_deg: ClassVar[float] = 5.0
    #: agreeing pairs an image needs to be trusted (a count: on repetitive scenes many are wrong).
    min_agreeing_pairs: ClassVar[int] = 2
    #: matches a pair needs to enter the estimate, the trust test and the pair-level verdict.
    min_pair_matches: ClassVar[int] = 15
    #: the estimate is used only with this many trusted images and this share of the registered.
    min_trusted_images: ClassVar[int] = 3
    min_trusted_share: ClassVar[float] = 0.5
    #: a pair with a larger share of failing matches is removed whole.
    max_pair_fail_share: ClassVar[float] = 0.8
    #: an untrusted image is placed again from the trusted part (absolute pose), needing these inliers.
    place_untrusted: ClassVar[bool] = True
    min_placed_inliers: ClassVar[int] = 30
    #: a pair's own rotation is estimated from at most this many of its matches (0: all).
    pair_rotation_matches: ClassVar[int] = 512
    #: the global mapper's bundle-adjustment rounds, retriangulation, and Ceres' function
    #: tolerance (the judging needs poses, not the last digits of a dense model).
    ba_iterations: ClassVar[int] = 3
    retriangulate: ClassVar[bool] = True
    ba_function_tolerance: ClassVar[float] = 1e-4
    #: the global positioning solves for the longest tracks until each image has this many
    #: (COLMAP's ``track_required_tracks_per_view``; 0: every track), again with every track
    #: where that registers fewer images; retriangulation then uses them all. Off: faster on
    #: large surveys, but it loses pose on repeated structure (docs/results.md, the match check).
    positioning_tracks_per_image: ClassVar[int] = 0
    #: look for a hinge (two image groups the estimate turned against each other) after each
    #: estimate: a mode of at least ``hinge_min_pairs`` pairs touching ``hinge_min_side_images``
    #: images on each side (:mod:`colmap_miho.verification.hinge`).
    look_for_hinges: ClassVar[bool] = True
    hinge_min_pairs: ClassVar[int] = 3
    hinge_min_side_images: ClassVar[int] = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", MatchCheckMode.parse(self.mode, "mode"))
        check_bounds(self)
        if self.min_threshold_px > self.max_threshold_px:
            raise ValueError("need min_threshold_px <= max_threshold_px, got "
                             f"{self.min_threshold_px} and {self.max_threshold_px}")

    @property
    def enabled(self) -> bool:
        """The stage runs (mode is not "off")."""
        return self.mode != MatchCheckMode.OFF
