"""Configuration of the MOP / MOP+MiHo filter (pure dataclass, no torch import)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from ..enums import Assignment, FilterMethod, MihoThreshold, Sampling
from ..validation import (
    MAX_ITERS,
    MAX_MATCHES,
    MAX_THRESHOLD_PX,
    MIN_THRESHOLD_PX,
    PX,
    check_bounds,
    within,
)

#: c_max of MOP+MiHo when ``max_iters`` is not given.
MIHO_MAX_ITERS = 500
#: c_max of the MOP variants when ``max_iters`` is not given (the paper's).
MOP_MAX_ITERS = 2000


@dataclass(frozen=True, kw_only=True)
class FilterConfig:
    """MOP / MOP+MiHo (paper App. A; its defaults unless said otherwise).

    Attributes:
        method: the filter variant (:class:`~colmap_miho.enums.FilterMethod`).
        t_l: relaxed inlier threshold, pixels (max two-way transfer error).
        t_h: strict threshold, pixels; None: t_l / 2.
        min_inliers: n, the least inliers of a kept homography; None: 12 for MOP, 8 for MiHo.
        max_iters: c_max, most RANSAC hypotheses per round; None: :data:`MIHO_MAX_ITERS` for
            MOP+MiHo(*), the paper's 2000 for the MOP variants.
        miho_threshold: what MiHo's thresholds bound: "half" (each half-match, the paper's),
            "full" (the full match, as MOP) or "full_search" (full while searching planes,
            half when assigning matches).
        coherence: drop planes whose matches mostly sit among other planes' matches that
            contradict them (:mod:`.coherence`): fewer spurious planes of repeated texture.
        batch_growth: most factor by which a round's hypothesis batch may outgrow the one
            before it (0: no limit but ``8 x batch_size``).

    The class constants below are the paper's (or the reference's) fixed values; the
    alternative rules they name (uniform sampling, the reference's assignment) are measured
    by the benchmarks, not recipe keys.
    """

    method: FilterMethod = FilterMethod.MOP_MIHO
    t_l: float = field(default=15.0, metadata=within(MIN_THRESHOLD_PX, MAX_THRESHOLD_PX, PX))
    t_h: float | None = field(default=None, metadata=within(MIN_THRESHOLD_PX, MAX_THRESHOLD_PX, PX))
    min_inliers: int | None = field(default=None, metadata=within(
        4, MAX_MATCHES, "a homography needs 4 matches; no pair holds more"))
    max_iters: int | None = field(default=2000, metadata=within(
        1, MAX_ITERS, "RANSAC hypotheses per round, each scored on every match"))
    miho_threshold: MihoThreshold = MihoThreshold.FULL_SEARCH
    coherence: bool = False
    batch_growth: float = field(default=0.0, metadata=within(0, 8, "batches never exceed 8 x batch_size"))

    #: c_f*, consecutive failed rounds that stop MOP.
    max_failures: ClassVar[int] = 3
    #: c_min, least RANSAC hypotheses per round.
    min_iters: ClassVar[int] = 50
    #: p of the adaptive RANSAC bound (the reference's).
    confidence: ClassVar[float] = 0.9
    #: least smallest singular value of the normalised DLT system.
    min_singular_value: ClassVar[float] = 0.05
    #: z, the top-z sub-optimal models kept and scored again every round.
    buffer_size: ClassVar[int] = 5
    #: MiHo's 90-degree rotation pre-alignment (App. C), mirrored image 2 included, scored
    #: on this many random match pairs (0: all).
    rotation_fix: ClassVar[bool] = True
    rotation_fix_reflections: ClassVar[bool] = True
    rotation_pairs: ClassVar[int] = 20000
    #: minimal samples: "local" (NAPSAC-style, :mod:`.sampling`: ``local_fraction`` of them
    #: among each seed's ``local_neighbours``) or the paper's "uniform".
    sampling: ClassVar[Sampling] = Sampling.LOCAL
    local_neighbours: ClassVar[int] = 8
    local_fraction: ClassVar[float] = 0.75
    #: hypotheses per vectorised batch (the adaptive stopping test runs between batches).
    batch_size: ClassVar[int] = 128
    #: least-squares refits of the best model on its inliers, each kept if it loses none.
    refit_iters: ClassVar[int] = 1
    #: App. A.4's rule giving each kept match one homography ("paper", "median", "reference").
    assignment: ClassVar[Assignment] = Assignment.PAPER

    def __post_init__(self) -> None:
        object.__setattr__(self, "method", FilterMethod.parse(self.method, "method"))
        object.__setattr__(self, "miho_threshold",
                           MihoThreshold.parse(self.miho_threshold, "miho_threshold"))
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
