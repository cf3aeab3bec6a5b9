"""Configuration of the pair check and the match check (pure dataclasses, no I/O)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..enums import MatchCheckMode, PairCheckMode
from ..validation import MAX_MATCHES, MAX_SEED, MAX_THRESHOLD_PX, PX, SHARE, check_bounds, within


@dataclass(frozen=True, kw_only=True)
class PairCheckConfig:
    """Parameters of the pair check: which image pairs the rest of the pair graph contradicts
    (see :mod:`colmap_miho.verification.pair_graph`).

    In each triangle of the pair graph (images i, j, k matched pairwise) every pair's matches
    are carried into the third image by the other two pairs, through their matches or by
    epipolar transfer; a transfer closes when it lands within ``transfer_tol_px`` of the
    expected keypoint. A pair's transfers that mostly fail blame the two carrying pairs (and
    the pair itself, ``transferred_votes``), the others support them; the votes are weighted
    by the trust of the triangle's other pairs, pairs are removed worst first, and a removed
    pair whose tracks the kept pairs confirm is kept after all.

    Defaults chosen with ``benchmarks/bench_pair_check.py`` on the demo, Middlebury temple and
    Strecha fountain and entry, default and permissive COLMAP matching, and on the synthetic
    doppelganger scenes (several seeds); what they find there is in ``docs/results.md``.

    Attributes:
        enabled: run the check (``refine``: between the filter and the refinement).
        mode: "remove" (the pair's matches are dropped from the output) or "flag" (only
            reported).
        transfer_tol_px: pixels; a transfer that lands at most this far from the expected
            keypoint closes (SIFT places one keypoint several times, with other
            orientations, within a pixel or two).
        min_transfers: counted transfers of one pair into one triangle's third image needed
            for a vote; fewer: that transfer does not vote.
        min_closed_share: a pair's transfer into a triangle's third image fails when the
            closed share of its counted transfers is below this.
        transferred_votes: a counted transfer votes on the pair transferred too, not only on
            its two carriers (the transfer is a loop through all three pairs).
        trust_iterations: rounds of trust weighting before each removal (0: every vote counts
            fully). A triangle's votes on a pair count as much as the triangle's two
            other pairs are trusted, and a pair's trust is ``(1 - its weighted blame share)
            ** trust_power``: two wrong pairs that agree with each other close their shared
            triangles, but each is blamed by its other triangles, so the support they give
            each other fades (see :func:`~colmap_miho.verification.pair_graph.settle_trust`).
        trust_power: exponent of the trust of a pair from its weighted blame share (larger: a
            blamed pair's votes fade faster).
        confirm_triangles: a pair the vote removed is kept when its own matches, carried
            through the matches of two kept pairs trusted at least ``confirm_trust``, close
            (at least ``min_transfers``, a share of at least ``confirm_share``) in this many
            triangles (0: off). Wrong pairs join different scene points, so only other wrong
            pairs can confirm them; a correct pair whose fundamental matrix is inaccurate
            (few matches, wide baseline) is confirmed by its neighbours' tracks.
        confirm_share / confirm_trust: see ``confirm_triangles``.
        min_blame: blames a pair needs before it can be removed.
        min_blame_share: share of blames among a pair's votes needed to remove it.
        min_angle_deg: degrees; epipolar transfers whose two lines meet at a smaller angle
            (nearly collinear camera centres) are not counted.
        max_transfers: matches per pair carried into each third image (spread over its rows);
            bounds the time per triangle.
        f_threshold_px: pixels; Sampson distance of the inliers of the fundamental matrix
            fitted to each pair's matches.
        min_f_matches: pairs with fewer matches get no fundamental matrix (too few to fit one
            accurately): their triangles use matches only.
        seed: base seed of the fundamental-matrix sampling (per pair: seed and its image ids).
    """

    enabled: bool = False
    mode: PairCheckMode = PairCheckMode.REMOVE
    transfer_tol_px: float = field(default=4.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    min_transfers: int = field(default=8, metadata=within(1, MAX_MATCHES, "no pair holds more matches"))
    min_closed_share: float = field(default=0.4, metadata=within(0, 1, SHARE))
    transferred_votes: bool = True
    trust_iterations: int = field(default=10, metadata=within(
        0, 100, "rounds over every triangle before each removal; the trust settles within a few"))
    trust_power: float = field(default=2.0, metadata=within(0, 100, "an exponent of a share", lo_open=True))
    confirm_triangles: int = field(default=3, metadata=within(0, MAX_MATCHES, "triangles of a pair"))
    confirm_share: float = field(default=0.8, metadata=within(0, 1, SHARE, lo_open=True))
    confirm_trust: float = field(default=0.5, metadata=within(0, 1, SHARE))
    min_blame: int = field(default=2, metadata=within(1, MAX_MATCHES, "votes on a pair"))
    min_blame_share: float = field(default=0.55, metadata=within(0, 1, SHARE, lo_open=True))
    min_angle_deg: float = field(default=5.0, metadata=within(0, 90, "degrees, below a right angle", hi_open=True))
    max_transfers: int = field(default=200, metadata=within(1, 100_000, "matches carried into every third image"))
    f_threshold_px: float = field(default=1.5, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    min_f_matches: int = field(default=50, metadata=within(
        8, MAX_MATCHES, "the eight-point algorithm; no pair holds more"))
    seed: int = field(default=0, metadata=within(0, MAX_SEED, "a 32-bit seed"))

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", PairCheckMode.parse(self.mode, "mode"))
        check_bounds(self)


@dataclass(frozen=True, kw_only=True)
class MatchCheckConfig:
    """Parameters of the match check: every match judged against a global estimate of the
    cameras (the algorithm and why it is built so: ``docs/how-it-works.md``, the match check;
    measured figures: ``docs/results.md``, the match check).

    Attributes:
        mode: "remove": the matches the estimate contradicts are removed before the
            refinement (repeated structure that no check of a pair alone can see; where the
            estimate is not trusted, nothing is removed); "flag": judged and reported only;
            "off": no estimate.
        false_reject: the share of correct matches the threshold would remove if their
            distances were exactly exponential (0.0027: a normal's 3-sigma tail).
        min_threshold_px / max_threshold_px: pixels; bounds of the threshold. The floor keeps
            correct matches where the estimate fits very tightly (the tail is heavier than
            exponential); the cap bounds it when many wrong matches blow up the scale (a
            correct match lies within 4 px of its GT epipolar line).
        max_rotation_deg: a pair agrees with the estimate when the angle between its own
            relative rotation and the estimate's is at most this.
        min_agreeing_pairs: agreeing pairs an image needs to be trusted (a count, not a
            median: on repetitive scenes many pairs are wrong).
        min_pair_matches: a pair needs this many matches to enter the estimate, for its own
            relative rotation to count in the trust test, and for the pair-level verdict.
        min_trusted_images / min_trusted_share: the estimate is used only with at least this
            many trusted images and this share of its registered ones (otherwise nothing is
            removed).
        max_pair_fail_share: a pair whose share of failing matches exceeds this is removed whole.
        place_untrusted: place each image the check did not trust again from the trusted part
            of the estimate (absolute pose at ``max_threshold_px``, as incremental mapping
            registers an image), then test its trust again.
        min_placed_inliers: 2D-3D inliers such a new pose needs.
        estimate_matches_per_image: the global estimate is built from a sample of whole
            tracks, about this many match ends per image on average (0: every match;
            :func:`~colmap_miho.sfm.global_estimate.sampled_tracks`). The mapper's cost grows
            with the tracks it is given; the sample bounds it per image. The judging and the
            placements still use every match.
        pair_rotation_matches: each pair's own relative rotation (the trust test's) is estimated
            from at most this many of its matches, evenly spaced over them (0: all of them).
        ba_iterations / retriangulate: the global mapper's bundle-adjustment rounds and its
            retriangulation after them.
        ba_function_tolerance: the global mapper's bundle adjustments stop when an iteration
            lowers the cost by less than this share (Ceres' ``function_tolerance``; 0: its own
            1e-5): the judging needs poses, not the last digits of a dense model (the same pose
            outcome on every shared scene, less mapper time: docs/results.md, the match check).
        hinges: after each estimate, look for a hinge (two groups of images the estimate turned
            against each other: a tight mode of the pairs' disagreements, see
            :mod:`colmap_miho.verification.hinge`) and let the pairs' own coverage decide
            between the estimate and the other hypothesis; when it does not decide, the pairs
            between the two groups are left unjudged.
        hinge_min_pairs / hinge_min_side_images: a mode is a hinge when at least this many
            pairs disagree with the estimate by the same rotation, touching at least this many
            images on each side (one image turned alone is the trust test's case).
        rounds: global estimates at most; each later one is made from the last one's survivors
            among the images not trusted yet and those two pairs around them, and judges, with
            the first round's threshold, the pairs of the images newly trusted (stops once
            every placed image is trusted).
        seed: random seed of the global mapper and of the pairs' relative-pose RANSAC.
    """

    mode: MatchCheckMode = MatchCheckMode.REMOVE
    false_reject: float = field(default=0.0027, metadata=within(
        0, 0.5, "a probability in the tail of the residuals", lo_open=True, hi_open=True))
    min_threshold_px: float = field(default=2.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    max_threshold_px: float = field(default=4.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    max_rotation_deg: float = field(default=5.0, metadata=within(
        0, 180, "degrees between two rotations", lo_open=True, hi_open=True))
    min_agreeing_pairs: int = field(default=2, metadata=within(1, 10_000, "pairs of one image"))
    min_pair_matches: int = field(default=15, metadata=within(
        8, MAX_MATCHES, "the eight-point algorithm; no pair holds more"))
    min_trusted_images: int = field(default=3, metadata=within(2, 1_000_000, "images"))
    min_trusted_share: float = field(default=0.5, metadata=within(0, 1, SHARE, lo_open=True))
    max_pair_fail_share: float = field(default=0.8, metadata=within(0, 1, SHARE, lo_open=True))
    place_untrusted: bool = True
    min_placed_inliers: int = field(default=30, metadata=within(
        6, MAX_MATCHES, "an absolute pose needs 6 correspondences"))
    estimate_matches_per_image: int = field(default=2000, metadata=within(
        0, 1_000_000_000, "match ends of an image (0: all)"))
    pair_rotation_matches: int = field(default=512, metadata=within(0, MAX_MATCHES, "matches of a pair (0: all)"))
    ba_iterations: int = field(default=3, metadata=within(1, 10, "rounds of bundle adjustment, each a full adjustment"))
    retriangulate: bool = True
    ba_function_tolerance: float = field(default=1e-4, metadata=within(0, 0.1, "a relative cost decrease"))
    hinges: bool = True
    hinge_min_pairs: int = field(default=3, metadata=within(2, 1_000_000, "pairs across a hinge"))
    hinge_min_side_images: int = field(default=2, metadata=within(1, 1_000_000, "images on one side of a hinge"))
    rounds: int = field(default=2, metadata=within(1, 5, "global-mapper runs"))
    seed: int = field(default=0, metadata=within(0, MAX_SEED, "a 32-bit seed"))

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
