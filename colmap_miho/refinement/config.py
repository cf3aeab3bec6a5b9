"""Configuration of the refinement: NCC (``[ncc]``), least-squares matching (``[lsm]``), the
patch rectification (``[rectify]``) and the track walk (``[tracks]``); pure dataclasses, no
torch import. The measurements behind the defaults are in ``docs/results.md``."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar

from ..enums import Device, MoveSide, Perturbations, Rectification, StrEnum
from ..validation import (
    MAX_BLUR_PX,
    MAX_LOCAL_NEIGHBOURS,
    MAX_THRESHOLD_PX,
    MAX_WINDOW_RADIUS_PX,
    NCC,
    PX,
    check_bounds,
    require_at_most,
    within,
)
from ..validation import MAX_NCC_BATCH as MAX_NCC_BATCH

#: matches per batched NCC call when ``NCCConfig.batch_size`` is None, per device type.
DEFAULT_BATCH_SIZE = {"cpu": 2048, "cuda": 4096}


@dataclass(frozen=True, kw_only=True)
class LSMConfig:
    """Least-squares matching from the NCC peak (:mod:`.lsm.step`: affine + gain/offset,
    bicubic reads); its position replaces the parabola's where it converged near the peak.

    Attributes:
        enabled: run LSM after the NCC peak.
        radius: LSM template half size, pixels (0: ``ncc.template_radius``).
        antialias: 0 (off), or the blur (pixels) assumed in each image: the view that sees a
            match finer is read smoothed to the coarser one's blur.
        max_shift_px: LSM's position is used only within this distance of the NCC peak.
        tol_px: converged once the shift update is below this, pixels.
    """

    enabled: bool = True
    radius: int = field(default=8, metadata=within(0, MAX_WINDOW_RADIUS_PX, "pixels"))
    antialias: float = field(default=0.5, metadata=within(
        0, MAX_BLUR_PX, "pixels of blur; wider than the LSM window is meaningless"))
    max_shift_px: float = field(default=2.0, metadata=within(
        0, MAX_WINDOW_RADIUS_PX, "pixels, within the LSM window", lo_open=True))
    tol_px: float = field(default=0.01, metadata=within(0, 0.1, "pixels", lo_open=True))

    #: estimate the 4 affine terms (False: shift and radiometry only).
    affine: ClassVar[bool] = True
    #: most Gauss-Newton steps; an unconverged match keeps its NCC position.
    max_iterations: ClassVar[int] = 10
    #: LSM's position is used only if its shift's a-posteriori standard deviation is below this.
    max_sigma_px: ClassVar[float] = 0.1

    def __post_init__(self) -> None:
        check_bounds(self)


@dataclass(frozen=True, kw_only=True)
class RectifyConfig:
    """The patch homography pairs of the track walk (:mod:`.rectify.local_affine`).

    Attributes:
        mode: "filter" (the filter's plane), "local" (a local affine fit that follows
            relief) or "both" (the higher NCC peak wins).
        neighbours: matches (itself included) of each local affine fit.
        max_residual_px: neighbours off the first fit by more than this leave the second.
    """

    mode: Rectification = Rectification.BOTH
    neighbours: int = field(default=12, metadata=within(6, MAX_LOCAL_NEIGHBOURS, "neighbours of every local fit"))
    max_residual_px: float = field(default=2.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", Rectification.parse(self.mode, "mode"))
        check_bounds(self)


@dataclass(frozen=True, kw_only=True)
class NCCConfig:
    """The NCC refinement (paper Sec. 3.3, App. E): a template of radius r around the fixed
    keypoint searched over offsets up to s around the moving one, both resampled through the
    match's patch homography pair; then ``lsm`` from the peak. The defaults are the track
    walk's; :meth:`pairwise` gives the paper's pairwise values.

    Attributes:
        template_radius: r, template half size ((2r + 1)^2 pixels).
        search_radius: s, half size of the offset search; r + s <= ``MAX_WINDOW_RADIUS_PX``.
        inner_radius: 0 (off), or s0 in [1, s): search up to s0 first and the full s only
            where a peak lies on that window's border.
        min_ncc: a move's NCC peak must reach this (-1: no floor).
        move: which side may move: "1", "2" or "auto" (the higher NCC peak's direction).
        batch_size: matches per batched call (bounds memory); None: ``DEFAULT_BATCH_SIZE``.
        device: "auto" follows CUDA inputs, else CUDA when available, else the CPU.
        lsm, rectify: the ``[lsm]`` and ``[rectify]`` tables.

    The class constants below are fixed; the paper's variants they switch (its shape
    perturbations, NCC*'s ellipse mask) are measured by the benchmarks, not recipe keys.
    """

    template_radius: int = field(default=6, metadata=within(
        1, MAX_WINDOW_RADIUS_PX, "pixels; the window of every match is held in memory"))
    search_radius: int = field(default=10, metadata=within(
        1, MAX_WINDOW_RADIUS_PX, "pixels; the window of every match is held in memory"))
    inner_radius: int = field(default=2, metadata=within(0, MAX_WINDOW_RADIUS_PX, "pixels"))
    min_ncc: float = field(default=-1.0, metadata=within(-1, 1, NCC))
    move: MoveSide = MoveSide.AUTO
    batch_size: int | None = field(default=None, metadata=within(1, MAX_NCC_BATCH, "matches held in memory at once"))
    device: Device = Device.AUTO
    lsm: LSMConfig = field(default_factory=LSMConfig)
    rectify: RectifyConfig = field(default_factory=RectifyConfig)

    #: template shapes tried (App. E): "none"; "paper" (25) and "small" (5) were never more accurate.
    perturbations: ClassVar[Perturbations] = Perturbations.NONE
    #: with several shapes, choose the shape on a stride-2 grid first.
    coarse_shapes: ClassVar[bool] = True
    #: also try the base pair (identity, or the keypoint affine frames).
    use_base_pair: ClassVar[bool] = True
    #: NCC*: restrict the search to the template's structure-tensor ellipse.
    ellipse_mask: ClassVar[bool] = False
    #: reject a move whose peak lies on the search window's border (the true one may lie outside).
    reject_border: ClassVar[bool] = True
    #: templates with a lower intensity standard deviation ([0, 1] scale) are flat, never moved.
    min_template_std: ClassVar[float] = 0.01
    #: re-centred parabola fits after the first (the single fit is biased towards integers).
    subpixel_iterations: ClassVar[int] = 3

    def __post_init__(self) -> None:
        choices: dict[str, type[StrEnum]] = {"move": MoveSide, "device": Device}
        for name, choice in choices.items():
            object.__setattr__(self, name, choice.parse(getattr(self, name), name))
        check_bounds(self)
        require_at_most("template_radius + search_radius", self.template_radius + self.search_radius,
                        MAX_WINDOW_RADIUS_PX, "the search window of every match is held in memory")
        require_at_most("lsm.antialias", self.lsm.antialias, self.lsm_window,
                        "pixels of blur, at most the LSM template radius (lsm.radius, else ncc.template_radius)")

    @property
    def lsm_window(self) -> int:
        """The LSM template radius (pixels): ``lsm.radius``, else ``template_radius``."""
        return self.lsm.radius or self.template_radius

    @classmethod
    def pairwise(cls, **changes) -> NCCConfig:
        """The paper's pairwise refinement (:data:`PAIRWISE`), with ``changes`` (``lsm`` and
        ``rectify`` may be dicts of changes to its tables)."""
        for name, base in (("lsm", PAIRWISE["lsm"]), ("rectify", RectifyConfig())):
            if isinstance(changes.get(name), dict):
                changes[name] = replace(base, **changes[name])
        return cls(**{**PAIRWISE, **changes})


#: What the paper's pairwise refinement changes from the walk's defaults (:meth:`NCCConfig.pairwise`):
#: 21x21 templates, every offset searched at once, NCC without least-squares matching.
PAIRWISE: dict = {"template_radius": 10, "inner_radius": 0,
                  "lsm": LSMConfig(enabled=False, radius=0, antialias=0.0, max_shift_px=0.5, tol_px=0.005)}


@dataclass(frozen=True, kw_only=True)
class TrackConfig:
    """The track-consistent walk (its rules: :mod:`colmap_miho.refinement.tracks.build`).

    Attributes:
        max_images_in_memory: decoded images the lazy loader keeps (and one batched call uses).
        multiphoto_lsm: after the walk, align every observation of a track of three or more
            jointly to a consensus template, the anchor fixed (:mod:`.tracks.multiphoto`).
        multiphoto_iterations: consensus passes of that joint step.
        far_move_check: a keypoint moves farther than ``rectify.max_residual_px`` only where
            the homography pair's prediction supports the new position (else a repeated
            texture's peak; counted as ``rejected_far``).
    """

    max_images_in_memory: int = field(default=8, metadata=within(2, 1024, "decoded images held at once"))
    multiphoto_lsm: bool = False
    multiphoto_iterations: int = field(default=3, metadata=within(1, 10, "consensus passes per track"))
    far_move_check: bool = True

    #: refine all pairs of a walk level in one NCC call (bit-identical results); None: batched
    #: with the built-in refiner, one call per pair with a custom ``refine_fn``.
    batch_pairs: ClassVar[bool | None] = None
    #: pixels: two keypoints of one image in one track closer than this are duplicates (SIFT
    #: keeps one per orientation) and are walked; farther apart they freeze the track.
    duplicate_px: ClassVar[float] = 1.0

    def __post_init__(self) -> None:
        check_bounds(self)
