"""Configuration of the MOP / MOP+MiHo filter (pure dataclass, no torch import)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..enums import Assignment, FilterMethod, MihoThreshold, Sampling
from ..validation import (
    MAX_HYPOTHESES_BATCH,
    MAX_ITERS,
    MAX_LOCAL_NEIGHBOURS,
    MAX_MATCHES,
    MAX_THRESHOLD_PX,
    MIN_THRESHOLD_PX,
    PX,
    SHARE,
    check_bounds,
    within,
)

#: c_max of MOP+MiHo when ``max_iters`` is not given.
MIHO_MAX_ITERS = 500
#: c_max of the MOP variants when ``max_iters`` is not given (the paper's).
MOP_MAX_ITERS = 2000


@dataclass(frozen=True, kw_only=True)
class FilterConfig:
    """Parameters of MOP / MOP+MiHo. Defaults are the paper's (App. A).

    Attributes:
        method: filter variant, see :class:`~colmap_miho.enums.FilterMethod`.
        t_l: relaxed inlier threshold t_l in pixels (max two-way transfer error).
        t_h: strict threshold t_h in pixels; ``None`` means the paper's t_l / 2
            (the reference implementation uses 7).
        min_inliers: n, the least inliers a kept homography needs; ``None`` means the
            paper's 12 for MOP and 8 for MiHo.
        max_failures: c_f*, consecutive failures that stop MOP (paper: 3).
        min_iters: c_min, least RANSAC hypotheses per round (paper: 50).
        max_iters: c_max, most RANSAC hypotheses per round (paper: 2000); ``None`` means
            :data:`MIHO_MAX_ITERS` for MOP+MiHo and MOP+MiHo* (the authors' ablation: 500
            iterations per round as accurate as 2000) and the paper's 2000 for the MOP
            variants (their 4-point samples in one frame need more draws where almost every
            match is an outlier).
        confidence: p of the adaptive RANSAC bound (reference: 0.9).
        min_singular_value: threshold on the smallest singular value of the normalised
            DLT system (paper: 0.05).
        buffer_size: z, size of the top-z sub-optimal model buffer (paper: 5).
        rotation_fix: MiHo's 90-degree rotation pre-alignment (App. C).
        sampling: ``"local"`` (default, NAPSAC-style guided minimal samples, see
            :mod:`~colmap_miho.filtering.sampling`) or ``"uniform"`` (the paper's), a
            :class:`~colmap_miho.enums.Sampling`.
        local_neighbours: neighbourhood size k of local sampling (joint (x1, x2) space).
        local_fraction: share of the minimal samples drawn locally (rest uniform).
        batch_size: hypotheses drawn per vectorised batch; the adaptive stopping test runs
            between batches.
        batch_growth: most factor by which a round's batch may outgrow the one before it
            (batches never exceed ``8 x batch_size``); the adaptive bound is checked between
            batches, so small steps stop a round near the bound of the inlier ratio it has
            found instead of drawing a large batch sized by an early, weak model. 0: no limit
            but ``8 x batch_size``.
        refit_iters: least-squares refits of the best model on its inliers, each kept only
            if it does not lose inliers (paper: 1).
        rotation_fix_reflections: let the rotation fix also consider mirrored image 2
            (App. C says it "can easily be extended"); for MOP+MiHo* a mirrored best
            candidate makes the pair fail (reflections are excluded by that variant).
        rotation_pairs: random match pairs scored by the rotation fix (0 = all pairs).
        miho_threshold: what MiHo's thresholds t_l and t_h bound. ``"half"`` (the paper's
            and the reference's): each of the four transfer errors of the two half-matches
            against the midpoint, so a full match may be about twice as far off as MOP
            allows. ``"full"``: the full match, i.e. twice the largest half-match error
            (which bounds ``|H1 x1 - H2 x2|`` in the midpoint frame), the same tolerance as
            MOP's. ``"full_search"`` (default, chosen on the hard-pairs benchmark): the
            full match while MOP searches planes, the half-matches when the found planes
            keep and assign matches. Ignored by the other methods.
        assignment: App. A.4 rule giving each kept match one homography. ``"paper"``: the
            compatible homography with the least error among those whose support is at
            least q, the median support of the (top 5) compatible ones; with exactly two
            compatible homographies both are eligible (their errors decide, as in the
            reference; the plain median, their mean, would always pick the larger plane).
            ``"median"``: the plain median in every case. ``"reference"``: the reference
            implementation's rule: compatibility and supports from each homography's t_l
            inliers in the pool of the round that found it, and a match compatible with
            none is still kept, with its least-error homography, when that error is within
            t_l.
        coherence: after assignment, drop the homographies whose matches mostly sit among
            matches of other planes that they contradict (in both images), and re-assign
            their matches (:mod:`colmap_miho.filtering.coherence`). Removes spurious planes
            made of repeated-texture mismatches; off by default because it also drops a
            few correct matches on multi-plane scenes.
    """

    method: FilterMethod = FilterMethod.MOP_MIHO
    t_l: float = field(default=15.0, metadata=within(MIN_THRESHOLD_PX, MAX_THRESHOLD_PX, PX))
    t_h: float | None = field(default=None, metadata=within(MIN_THRESHOLD_PX, MAX_THRESHOLD_PX, PX))
    min_inliers: int | None = field(default=None, metadata=within(
        4, MAX_MATCHES, "a homography needs 4 matches; no pair holds more"))
    max_failures: int = field(default=3, metadata=within(1, 100, "each failure is a whole RANSAC round"))
    min_iters: int = field(default=50, metadata=within(1, MAX_ITERS, "RANSAC hypotheses per round"))
    max_iters: int | None = field(default=2000, metadata=within(
        1, MAX_ITERS, "RANSAC hypotheses per round, each scored on every match"))
    confidence: float = field(default=0.9, metadata=within(0, 1, "a probability", lo_open=True, hi_open=True))
    min_singular_value: float = field(default=0.05, metadata=within(0, 1, "a singular value of a normalised system"))
    buffer_size: int = field(default=5, metadata=within(0, 100, "models kept and scored again every round"))
    rotation_fix: bool = True
    sampling: Sampling = Sampling.LOCAL
    local_neighbours: int = field(default=8, metadata=within(3, MAX_LOCAL_NEIGHBOURS, "neighbours held per match"))
    local_fraction: float = field(default=0.75, metadata=within(0, 1, SHARE))
    batch_size: int = field(default=128, metadata=within(
        1, MAX_HYPOTHESES_BATCH, "hypotheses scored at once are held in memory"))
    refit_iters: int = field(default=1, metadata=within(0, 100, "least-squares refits of each kept model"))
    rotation_fix_reflections: bool = True
    rotation_pairs: int = field(default=20000, metadata=within(
        0, 10_000_000, "match pairs scored at once are held in memory"))
    miho_threshold: MihoThreshold = MihoThreshold.FULL_SEARCH
    assignment: Assignment = Assignment.PAPER
    coherence: bool = False
    batch_growth: float = field(default=0.0, metadata=within(0, 8, "batches never exceed 8 x batch_size"))

    def __post_init__(self) -> None:
        object.__setattr__(self, "method", FilterMethod.parse(self.method, "method"))
        object.__setattr__(self, "sampling", Sampling.parse(self.sampling, "sampling"))
        object.__setattr__(self, "miho_threshold",
                           MihoThreshold.parse(self.miho_threshold, "miho_threshold"))
        object.__setattr__(self, "assignment", Assignment.parse(self.assignment, "assignment"))
        check_bounds(self)
        if self.t_h is not None and not self.t_h <= self.t_l:
            raise ValueError(f"t_h must be in [{MIN_THRESHOLD_PX}, t_l={self.t_l}] pixels, got {self.t_h}")
        if not self.min_iters <= self.iteration_cap:
            raise ValueError(
                f"need 1 <= min_iters <= max_iters, got min_iters={self.min_iters}, "
                f"max_iters={self.iteration_cap}"
            )
        if 0 < self.batch_growth < 1:
            raise ValueError(f"batch_growth must be 0 or >= 1, got {self.batch_growth}")

    @property
    def is_miho(self) -> bool:
        return self.method in (FilterMethod.MOP_MIHO, FilterMethod.MOP_MIHO_STAR)

    @property
    def reflection_check(self) -> bool:
        return self.method in (FilterMethod.MOP_STAR, FilterMethod.MOP_MIHO_STAR)

    @property
    def strict_threshold(self) -> float:
        return self.t_l / 2 if self.t_h is None else self.t_h

    @property
    def iteration_cap(self) -> int:
        """c_max: ``max_iters``, or its method's default when ``None``."""
        if self.max_iters is not None:
            return self.max_iters
        return MIHO_MAX_ITERS if self.is_miho else MOP_MAX_ITERS

    @property
    def inlier_count(self) -> int:
        if self.min_inliers is not None:
            return self.min_inliers
        return 8 if self.is_miho else 12
