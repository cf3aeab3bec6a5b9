"""Configuration of NCC refinement (pure dataclasses, no torch import)."""

from __future__ import annotations

from dataclasses import dataclass, field

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

#: matches per batched NCC call when ``NCCConfig.batch_size`` is None, per device type (on
#: the CPU, large enough that the fixed cost of a call's few hundred small tensor operations
#: is spread over many matches; the chunk's search windows then take tens of MB).
DEFAULT_BATCH_SIZE = {"cpu": 2048, "cuda": 4096}
#: the closed choices of :class:`NCCConfig`, parsed from strings (recipes, ``--set``).
_CHOICES: dict[str, type[StrEnum]] = {"move": MoveSide, "perturbations": Perturbations, "device": Device,
            "rectification": Rectification}


@dataclass(frozen=True, kw_only=True)
class NCCConfig:
    """Parameters of the pairwise NCC refinement and of its track walk (paper Sec. 3.3, App. E).

    A template of radius r around the fixed keypoint is searched over offsets up to s around
    the moving keypoint, both resampled through the match's patch homography pair. NCC
    values are in [-1, 1]; lengths are image pixels unless said otherwise. The defaults are
    the track walk's of the default recipe; :meth:`pairwise` gives the paper's pairwise values
    (:data:`PAIRWISE`), which :func:`~colmap_miho.refinement.pairwise.refine_pair` uses. The
    measurements behind them are in ``docs/results.md`` ("NCC and the track walk",
    "Least-squares matching").

    Attributes:
        template_radius: r, template half size ((2r + 1)^2 patch): 6 (13x13) in the walk, where
            the paper's 21x21 span more relief (surface off the match's plane) and so raise the
            GT track residual of non-planar scenes; the paper's 10 (pairwise) is the most
            precise under an exact homography.
        search_radius: s, half size of the offset search (paper: 10); r + s <=
            ``MAX_WINDOW_RADIUS_PX``.
        perturbations: :class:`~colmap_miho.enums.Perturbations`, template shapes tried
            (applied to the template only): "none", "paper" (App. E's 5 rotations x 5
            factors) or "small" (identity, +-15 degrees, factors 5/6 and 6/5); cost grows
            with the number of shapes.
        use_base_pair: also try the base pair (identity, or the keypoint affine frames).
        ellipse_mask: NCC*, restrict the search to the template's structure-tensor ellipse
            (semi-axes s across the edge, ``s * sqrt(lambda_min / lambda_max)`` >= 0.5 px
            along it); with ``reject_border`` a peak the mask holds back is rejected.
        min_ncc: a move's NCC peak must reach this (-1: no floor).
        reject_border: reject a move whose peak lies on the search window's border (or is
            held back by the NCC* ellipse): the true peak may lie outside.
        min_template_std: templates whose intensity standard deviation ([0, 1] scale) is
            below this are flat and never moved (NCC is undefined on them).
        move: :class:`~colmap_miho.enums.MoveSide`, which side may move: "1", "2" or "auto"
            (the paper's: the direction with the higher NCC peak).
        coarse_shapes: with several shapes, choose the shape on a stride-2 offset grid, then
            search the full grid with it only (about 3x cheaper for "paper").
        subpixel_iterations: re-centred parabola fits after the first (0: the paper's single
            fit, biased towards integer offsets).
        batch_size: matches per batched call (bounds memory); None:
            ``DEFAULT_BATCH_SIZE`` of the device type.
        device: :class:`~colmap_miho.enums.Device`; "auto" follows CUDA inputs, else CUDA
            when available, else the CPU (:func:`colmap_miho.devices.resolve_device`).
        rectification: :class:`~colmap_miho.enums.Rectification`, the walk's patch
            homography pairs: "filter" (the filter's plane, ignores relief), "local" (a local
            affine fit that follows relief, :mod:`.rectify.local_affine`) or "both" (higher NCC wins).
        local_affine_neighbours: matches (itself included) of each local affine fit.
        local_affine_max_residual_px: neighbours off the first local fit by more than this are
            dropped from the second.
        lsm: refine the NCC peak by least-squares matching (:mod:`.lsm.align`: affine + gain/offset,
            bicubic reads) and take LSM's position where it converged, stayed near the NCC
            peak and is precise (the tests below); elsewhere the iterated parabolas.
        lsm_radius: LSM template half size (0: ``template_radius``); 8 (17x17): more precise
            than 13x13 on the Strecha scenes and the demo, and still better than NCC alone on
            the Middlebury temple.
        lsm_affine: estimate the 4 affine terms; False: shift and radiometry only.
        lsm_max_iterations: most Gauss-Newton steps; an unconverged match keeps its NCC
            position.
        lsm_tol_px: converged once the shift update is below this (common-frame pixels);
            0.01, a tenth of the precision bound, gave lower median, mean and p90 than 0.005
            on every scene and setting.
        lsm_max_shift_px: LSM's position is used only within this distance (max over x and
            y, common-frame pixels) of the NCC peak (on every scene and setting the residual
            falls as the bound grows from 0.5 to 2 px) ...
        lsm_max_sigma_px: ... and only if its shift's a-posteriori standard deviation
            (largest semi-axis of the error ellipse) is below this.
        lsm_antialias: 0 (off), or the blur (pixels, at most the LSM radius) assumed in each
            image (0.5: a camera image's own): a view that sees the match finer is read
            smoothed to the coarser one's blur (:mod:`.lsm.step`).
        lsm_only: a move LSM does not accept is rejected (counted as ``rejected_lsm``)
            instead of placed by the iterated parabolas.
        match_blur: smooth the sharper image of each pair to the other's blur, estimated from
            the pair's matches (:mod:`.ncc.blur`); a match's result then depends on the other
            matches of its pair in the call.
        inner_radius: 0 (off), or s0 in [1, s): search offsets up to s0 first and the full
            ``search_radius`` only where some pass peaks on that window's border (or the
            ellipse holds it back); a match peaking inside keeps that local maximum (2: about
            a third less CPU in the walk, the accuracy within its seed spread).
    """

    template_radius: int = field(default=6, metadata=within(
        1, MAX_WINDOW_RADIUS_PX, "pixels; the window of every match is held in memory"))
    search_radius: int = field(default=10, metadata=within(
        1, MAX_WINDOW_RADIUS_PX, "pixels; the window of every match is held in memory"))
    perturbations: Perturbations = Perturbations.NONE
    use_base_pair: bool = True
    ellipse_mask: bool = False
    min_ncc: float = field(default=-1.0, metadata=within(-1, 1, NCC))
    reject_border: bool = True
    min_template_std: float = field(default=0.01, metadata=within(0, 1, "intensities are in [0, 1]"))
    move: MoveSide = MoveSide.AUTO
    coarse_shapes: bool = True
    subpixel_iterations: int = field(default=3, metadata=within(0, 10, "re-centred fits per match"))
    batch_size: int | None = field(default=None, metadata=within(1, MAX_NCC_BATCH, "matches held in memory at once"))
    device: Device = Device.AUTO
    rectification: Rectification = Rectification.BOTH
    local_affine_neighbours: int = field(default=12, metadata=within(
        6, MAX_LOCAL_NEIGHBOURS, "neighbours of every local fit"))
    local_affine_max_residual_px: float = field(default=2.0, metadata=within(0, MAX_THRESHOLD_PX, PX, lo_open=True))
    lsm: bool = True
    lsm_radius: int = field(default=8, metadata=within(0, MAX_WINDOW_RADIUS_PX, "pixels"))
    lsm_affine: bool = True
    lsm_max_iterations: int = field(default=10, metadata=within(1, 50, "Gauss-Newton steps per match"))
    lsm_tol_px: float = field(default=0.01, metadata=within(0, 0.1, "pixels", lo_open=True))
    lsm_max_shift_px: float = field(default=2.0, metadata=within(
        0, MAX_WINDOW_RADIUS_PX, "pixels, within the LSM window", lo_open=True))
    lsm_max_sigma_px: float = field(default=0.1, metadata=within(
        0, MAX_WINDOW_RADIUS_PX, "pixels, within the LSM window", lo_open=True))
    lsm_antialias: float = field(default=0.5, metadata=within(
        0, MAX_BLUR_PX, "pixels of blur; wider than the LSM window is meaningless"))
    lsm_only: bool = False
    match_blur: bool = False
    inner_radius: int = field(default=2, metadata=within(0, MAX_WINDOW_RADIUS_PX, "pixels"))

    def __post_init__(self) -> None:
        for name, choice in _CHOICES.items():
            object.__setattr__(self, name, choice.parse(getattr(self, name), name))
        check_bounds(self)
        require_at_most("template_radius + search_radius", self.template_radius + self.search_radius,
                        MAX_WINDOW_RADIUS_PX, "the search window of every match is held in memory")
        require_at_most("lsm_antialias", self.lsm_antialias, self.lsm_window,
                        "pixels of blur, at most the LSM template radius (lsm_radius, else template_radius)")

    @property
    def lsm_window(self) -> int:
        """The LSM template radius (pixels): ``lsm_radius``, else ``template_radius``."""
        return self.lsm_radius or self.template_radius

    @classmethod
    def pairwise(cls, **changes) -> NCCConfig:
        """The paper's pairwise refinement (:data:`PAIRWISE`: 21x21 templates, the full search,
        NCC alone), with ``changes``."""
        return cls(**{**PAIRWISE, **changes})


#: What the paper's pairwise refinement changes from the walk's defaults (:meth:`NCCConfig.pairwise`,
#: :func:`~colmap_miho.refinement.pairwise.refine_pair`): 21x21 templates, every offset searched at
#: once, NCC without least-squares matching (the ``lsm_*`` values those the LSM recipes were
#: measured against).
PAIRWISE: dict = {"template_radius": 10, "inner_radius": 0, "lsm": False, "lsm_radius": 0, "lsm_antialias": 0.0,
                  "lsm_max_shift_px": 0.5, "lsm_tol_px": 0.005}


@dataclass(frozen=True, kw_only=True)
class TrackConfig:
    """Parameters of the track-consistent refinement walk; its rules (anchor, reach,
    conflicts) are in :mod:`colmap_miho.refinement.tracks.build`.

    Attributes:
        max_images_in_memory: images the pipeline's lazy loader keeps, and the most images
            one batched call may use.
        duplicate_px: two keypoints of one image in one track closer than this are
            duplicates (SIFT keeps one per dominant orientation) and are walked; farther
            apart they freeze the track.
        batch_pairs: refine all image pairs of a walk level in one NCC call (fewer, larger
            calls; bit-identical results). None: batched with the built-in refiner, one call
            per pair with a custom ``refine_fn``.
        multiphoto_lsm: after the walk, align every observation of each track of three or
            more jointly to a consensus template, the anchor fixed
            (:mod:`colmap_miho.refinement.tracks.multiphoto`; uses the ``lsm_*`` fields of
            :class:`NCCConfig`).
        multiphoto_iterations: consensus passes of the joint step (0: the star pass alone).
        multiphoto_star_first: first align every observation to the anchor alone (the star of
            pairwise alignments), then run the consensus passes; False: the first template
            is built at the walk's positions.
        far_move_check: a keypoint moves farther than ``far_move_px`` only where the new
            position lies within ``far_move_px`` of where the match's homography pair puts
            the fixed partner, or nearer to it than before (with a distinct peak,
            ``far_move_ratio``): a far peak neither supports is most often a repeated
            texture's. Rejected moves keep the keypoint (counted as ``rejected_far``).
        far_move_px: pixels in the moving image; None: ``NCCConfig.local_affine_max_residual_px``
            (the local fit's inlier bound).
        far_move_ratio: Lowe's ratio test on 1 - NCC for a far move that only comes nearer to
            the prediction: ``1 - peak <= ratio (1 - second)``; 1: off (0.8 turned fewer
            matches right, ``docs/results.md``, "Matches that refinement turns wrong").
    """

    max_images_in_memory: int = field(default=8, metadata=within(2, 1024, "decoded images held at once"))
    batch_pairs: bool | None = None
    duplicate_px: float = field(default=1.0, metadata=within(
        0, MAX_WINDOW_RADIUS_PX, "pixels between keypoints of one image"))
    multiphoto_lsm: bool = False
    multiphoto_iterations: int = field(default=3, metadata=within(0, 10, "consensus passes per track"))
    multiphoto_star_first: bool = False
    far_move_check: bool = True
    far_move_px: float | None = field(default=None, metadata=within(
        0, MAX_WINDOW_RADIUS_PX, "pixels, within the search window", lo_open=True))
    far_move_ratio: float = field(default=1.0, metadata=within(
        0, 1, "a share of the old distance to the prediction", lo_open=True))

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.multiphoto_iterations == 0 and not self.multiphoto_star_first:
            raise ValueError("multiphoto_iterations = 0 needs multiphoto_star_first (no pass left)")
