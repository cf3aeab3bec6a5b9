"""Configuration of NCC refinement (pure dataclasses, no torch import)."""

from __future__ import annotations

from dataclasses import dataclass

from ..enums import CheckRule, Device, MoveSide, Perturbations, Rectification, StrEnum
from ..validation import MAX_NCC_BATCH as MAX_NCC_BATCH
from ..validation import MAX_WINDOW_RADIUS_PX, check_bounds, require_at_most

#: matches per batched NCC call when ``NCCConfig.batch_size`` is None, per device type (on
#: the CPU, large enough that the fixed cost of a call's few hundred small tensor operations
#: is spread over many matches; the chunk's search windows then take tens of MB).
DEFAULT_BATCH_SIZE = {"cpu": 2048, "cuda": 4096}
#: the closed choices of :class:`NCCConfig`, parsed from strings (recipes, ``--set``).
_CHOICES: dict[str, type[StrEnum]] = {"move": MoveSide, "perturbations": Perturbations, "device": Device,
            "rectification": Rectification, "check_rule": CheckRule}


@dataclass(frozen=True, kw_only=True)
class NCCConfig:
    """Parameters of the pairwise NCC refinement and of its track walk (paper Sec. 3.3, App. E).

    A template of radius r around the fixed keypoint is searched over offsets up to s around
    the moving keypoint, both resampled through the match's patch homography pair. NCC
    values are in [-1, 1]; lengths are image pixels unless said otherwise.

    Every numeric field's range is in :data:`colmap_miho.validation.BOUNDS` (checked first).

    Attributes:
        template_radius: r >= 1, template half size (pixels; (2r + 1)^2 patch). The paper's
            10 is the most precise under an exact homography; the shipped NCC recipes use 6,
            which suffers less from relief in the track walk.
        search_radius: s >= 1, half size of the offset search (pixels; paper: 10);
            r + s <= ``MAX_WINDOW_RADIUS_PX``.
        perturbations: :class:`~colmap_miho.enums.Perturbations`, the template shapes tried
            on the extended pair: "none" (the pair itself), "paper" (App. E's A_{rho,f},
            5 rotations x 5 factors, applied to the template only; the reference applies its
            own 25 anisotropic scalings x rotations by inverse sampling) or "small" (identity,
            +-15 degrees, factors 5/6 and 6/5). More shapes cost proportionally more.
        use_base_pair: also try the base pair (identity, or the keypoint affine frames).
        ellipse_mask: NCC*, restrict the search to the structure-tensor ellipse of the
            (unperturbed) template: semi-axis s along the gradient and
            ``s * sqrt(lambda_min / lambda_max)`` along the edge, floored at 0.5 px (the
            paper: about 1 px). With ``reject_border`` a peak held back by the mask (not a
            local maximum of the unmasked map) is rejected like a border peak.
        min_gain: >= 0, a move of at least one pixel is applied only if it raises NCC by at
            least this much.
        min_ncc: in [-1, 1], a move is applied only if its NCC peak reaches this (-1: no
            floor); a weak peak is more likely wrong than right.
        reject_border: reject moves whose peak lies on the border of the search window (or
            is held back by the NCC* ellipse): the true peak may lie outside it.
        cornerness_gate: skip edge-like patches (structure-tensor test): along an edge the
            peak is not located.
        min_cornerness: in [0, 1], threshold of the gate on lambda_min / lambda_max.
        min_template_std: >= 0, templates whose intensity standard deviation is below this
            ([0, 1] intensity scale; uint8 images are divided by 255) are flat and never
            moved (NCC is undefined on them).
        move: :class:`~colmap_miho.enums.MoveSide`, which side may move: "1", "2" or "auto"
            (the paper's: the direction with the higher NCC peak moves).
        coarse_shapes: with several template shapes, choose the shape by NCC on a stride-2
            grid of offsets, then search the full grid with that shape only (about 3x
            cheaper for "paper"); False evaluates every shape at every offset.
        subpixel_iterations: in [0, 10], re-centred fits after the parabola on the integer
            NCC map: the window is re-sampled at the sub-pixel estimate and fitted again on
            its 3x3 neighbourhood (0 = the paper's single fit, which is biased towards
            integer offsets).
        batch_size: >= 1 and <= ``MAX_NCC_BATCH``, matches per batched call (bounds memory);
            None picks ``DEFAULT_BATCH_SIZE`` for the device type (a GPU wants large calls).
        device: :class:`~colmap_miho.enums.Device`; "auto" is the device of CUDA tensor (or
            image stack) inputs, else CUDA when torch sees one, else the CPU
            (:func:`colmap_miho.devices.resolve_device`).
        rectification: :class:`~colmap_miho.enums.Rectification`, the patch homography
            pairs of the track walk: "filter" (the filter's plane of each match), "local" (a
            local affine fit to the ``local_affine_neighbours`` nearest matches of its
            cluster, :mod:`.rectify`) or "both" (each match searched with both; the higher
            NCC peak wins). The filter's planes ignore relief; a local fit follows it.
        local_affine_neighbours: >= 6, matches (the match included) of each local affine fit.
        check_radius: 0 (off), or the radius (pixels, not ``template_radius``) of a second
            template search that confirms each move (see ``check_rule``): a peak biased by
            the patch's content is rarely at the same place for both sizes.
        check_px: > 0, pixels within which the two template sizes must agree ("agree").
        check_rule: :class:`~colmap_miho.enums.CheckRule`: "agree" (a move stays only if the
            ``check_radius`` search moves the same keypoint to within ``check_px`` of it) or
            "ncc" (the ``check_radius`` template's move replaces the other where its NCC
            peak is higher by more than ``check_ncc_margin``).
        check_ncc_margin: in [0, 2], NCC margin of the "ncc" rule.
        local_affine_max_residual_px: > 0, neighbours off the first local fit by more than
            this many pixels are dropped from the second.
        lsm: from the NCC peak (integer peak and parabola), align the fixed keypoint's
            template to the moving side by least-squares matching (:mod:`.lsm`: affine +
            gain/offset, bicubic samples, both patches in the match's common frame) and move
            the keypoint to LSM's position where it passes the three tests below; elsewhere
            the iterated parabolas (``subpixel_iterations``) refine the NCC peak as without
            LSM. Off in this dataclass, on in the default recipe
            (``colmap_miho/recipes/mop_miho_lsm.toml``).
        lsm_radius: in [0, ``MAX_WINDOW_RADIUS_PX``], half size of the LSM template in pixels
            (0: ``template_radius``).
        lsm_radius_per_scale: >= 0; 0 (off), or LSM templates sized by the fixed keypoint: radius
            ``round(lsm_radius_per_scale * scale)`` pixels, clamped to [4, the fixed radius
            above], where the keypoints carry an affine shape (scale = sqrt |det| of the
            frame; COLMAP's 4- and 6-column keypoints); the fixed radius elsewhere.
        lsm_affine: estimate the 4 affine terms (8 parameters); False: shift and
            radiometry only.
        lsm_max_iterations: in [1, 50], Gauss-Newton steps at most; a match that has not
            converged by then keeps its NCC position.
        lsm_tol_px: in (0, 0.1], a match's Gauss-Newton iteration has converged once its shift
            update is below this (common-frame pixels).
        lsm_max_shift_px: > 0, LSM's position is used only within this distance (max over x
            and y, common-frame pixels) of the NCC peak.
        lsm_max_sigma_px: > 0, ... and only if the a-posteriori standard deviation of its
            shift (largest semi-axis of the error ellipse, common-frame pixels) is below this.
        lsm_antialias: pixels in [0, the LSM template radius]; 0 (off), or the blur assumed in each image: where one
            view sees a match at a finer scale than the other, LSM reads it smoothed to the
            coarser view's blur (:mod:`.lsm_step`).
        lsm_only: a move LSM does not accept is rejected (the keypoint keeps its position)
            rather than placed by the iterated parabolas; counted as ``rejected_lsm``.
        match_blur: before the search, smooth the sharper image of each image pair to the
            other's blur, estimated from the pair's own matches (:mod:`.blur`); counted as
            ``blur_pairs`` and ``blur_matched``. A match's result then depends on the other
            matches of its image pair in the call (through the estimate), not on other pairs.
        inner_radius: >= 0 pixels; 0 (off, as is any s0 >= s), or s0 in [1, s): search the
            offsets up to s0 first (every homography pair, every shape) and the full
            ``search_radius`` only for the matches where the peak of some pair (or shape)
            lies on the border of that smaller window (or is held back by the NCC* ellipse),
            so that a peak farther out is still followed. A match whose pairs all peak
            inside the smaller window keeps the best of those local maxima, where the full
            search would take a higher peak farther out. Which matches lie inside the image
            is decided on the full window either way.
        lsm_cubic_a: in [-1, 0], the cubic convolution parameter of LSM's bicubic reads:
            -0.75 (Keys; ``grid_sample``'s bicubic) or -0.5 (Catmull-Rom, which reproduces
            quadratics: less bias of a sub-pixel read). The torch path (CUDA) reads -0.75 with
            ``grid_sample`` and other values with its own gather of the 16 taps.
    """

    template_radius: int = 10
    search_radius: int = 10
    perturbations: Perturbations = Perturbations.NONE
    use_base_pair: bool = True
    ellipse_mask: bool = False
    min_gain: float = 0.0
    min_ncc: float = -1.0
    reject_border: bool = True
    cornerness_gate: bool = False
    min_cornerness: float = 0.1
    min_template_std: float = 0.01
    move: MoveSide = MoveSide.AUTO
    coarse_shapes: bool = True
    subpixel_iterations: int = 3
    batch_size: int | None = None
    device: Device = Device.AUTO
    rectification: Rectification = Rectification.BOTH
    check_radius: int = 0
    check_px: float = 0.25
    check_rule: CheckRule = CheckRule.AGREE
    check_ncc_margin: float = 0.03
    local_affine_neighbours: int = 12
    local_affine_max_residual_px: float = 2.0
    lsm: bool = False
    lsm_radius: int = 0
    lsm_radius_per_scale: float = 0.0
    lsm_affine: bool = True
    lsm_max_iterations: int = 10
    lsm_tol_px: float = 0.005
    lsm_max_shift_px: float = 0.5
    lsm_max_sigma_px: float = 0.1
    lsm_antialias: float = 0.0
    lsm_only: bool = False
    match_blur: bool = False
    inner_radius: int = 0
    lsm_cubic_a: float = -0.75

    def __post_init__(self) -> None:
        for name, choice in _CHOICES.items():
            object.__setattr__(self, name, choice.parse(getattr(self, name), name))
        check_bounds(self, "ncc")  # every key's range (colmap_miho.validation.BOUNDS)
        require_at_most("template_radius + search_radius", self.template_radius + self.search_radius,
                        MAX_WINDOW_RADIUS_PX, "the search window of every match is held in memory")
        require_at_most("check_radius + search_radius", self.check_radius + self.search_radius,
                        MAX_WINDOW_RADIUS_PX, "the check's search window of every match is held in memory")
        if self.check_radius == self.template_radius:
            raise ValueError(f"check_radius must be 0 (off) or >= 1 and not template_radius, "
                             f"got {self.check_radius}")
        lsm_window = self.lsm_radius or self.template_radius
        require_at_most("lsm_antialias", self.lsm_antialias, lsm_window,
                        "pixels of blur, at most the LSM template radius (lsm_radius, else template_radius)")


@dataclass(frozen=True, kw_only=True)
class TrackConfig:
    """Parameters of the track-consistent refinement walk.

    The rules of the walk (anchor, reach, conflicts) are in
    :mod:`colmap_miho.refinement.track_plan`.

    Attributes:
        max_images_in_memory: images the pipeline's lazy loader keeps, and the most images
            one batched call may use.
        duplicate_px: two keypoints of one image in one track closer than this (pixels) are
            duplicates (SIFT keeps one keypoint per dominant orientation at one position)
            and are walked; farther apart they freeze the track.
        batch_pairs: refine all image pairs of a walk level in one NCC call (images stacked,
            at most ``max_images_in_memory`` per call) instead of one call per pair and side
            (True). The result is bit-identical either way (a match's NCC does not depend on
            its call); the batched walk makes fewer, larger calls, which is faster on the CPU
            too. None (default): batched with the built-in refiner on every device; a custom
            ``refine_fn`` gets one call per pair.
        align_to_anchor: align every keypoint of a track to the track's anchor (one
            reference per track) rather than to the partner it is matched with: a keypoint
            two or more matches away from the anchor is searched against the anchor's patch,
            rectified through the chain of patch homography pairs that leads to it, so the
            errors of the keypoints between do not add up along the chain. False: each
            keypoint is aligned to its partner (which may itself have just moved).
        multiphoto_lsm: after the walk, align every observation of each track of three or
            more jointly to a consensus template of all of them, the anchor held fixed
            (:mod:`colmap_miho.refinement.multiphoto`; uses the ``lsm_*`` fields of
            :class:`NCCConfig`). False: the walk's result stands.
        multiphoto_iterations: in [0, 10], consensus passes of the joint step (rebuild the
            template from the aligned patches, then align to it); 0: the star pass alone.
        multiphoto_star_first: the joint step first aligns every observation to the anchor
            alone (the star of pairwise alignments, from the walk's result), then runs the
            consensus passes from there. False (default): the first template is built at the
            walk's positions.
        far_move_check: a keypoint moves farther than ``far_move_px`` only with evidence
            that the new position is right: it lies within ``far_move_px`` of where the
            match's homography pair (the local affine fit where there is one, else the filter's
            plane) puts the fixed partner, or it is nearer to that prediction than the keypoint
            was (and its NCC peak distinct, ``far_move_ratio``). A far NCC peak that neither
            the keypoint nor the geometry supports is most often the wrong peak of a repeated
            texture; such a keypoint keeps its position (the match is kept), counted as
            ``rejected_far``. False: every move the NCC search accepts is applied.
        far_move_px: > 0 pixels, or None (default): ``NCCConfig.local_affine_max_residual_px``,
            the local fit's inlier bound, i.e. the error its prediction is expected to stay
            within. Measured in the moving image.
        far_move_ratio: in (0, 1], the distinctness test of a far move that only brings the
            keypoint nearer to the prediction: Lowe's ratio test on the dissimilarity 1 - NCC,
            ``1 - peak <= ratio (1 - second)`` with ``second`` the best separated peak of the
            same map (0.8 would be Lowe's threshold for SIFT descriptor distances). 1 (default):
            off, every peak counts as distinct: at 0.8 the turned-wrong matches summed over the
            shared scenes and settings did not change (227 with either) while 18 fewer turned
            right (the demo and the four shared scenes, both matching settings).
    """

    max_images_in_memory: int = 8
    batch_pairs: bool | None = None
    duplicate_px: float = 1.0
    align_to_anchor: bool = False
    multiphoto_lsm: bool = False
    multiphoto_iterations: int = 3
    multiphoto_star_first: bool = False
    far_move_check: bool = True
    far_move_px: float | None = None
    far_move_ratio: float = 1.0

    def __post_init__(self) -> None:
        check_bounds(self, "tracks")  # every key's range (colmap_miho.validation.BOUNDS)
        if self.multiphoto_iterations == 0 and not self.multiphoto_star_first:
            raise ValueError("multiphoto_iterations = 0 needs multiphoto_star_first (no pass left)")
