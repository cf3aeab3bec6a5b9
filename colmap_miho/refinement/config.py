"""Configuration of NCC refinement (pure dataclasses, no torch import)."""

from __future__ import annotations

from dataclasses import dataclass

from ..enums import MoveSide
from ..validation import require_at_most, require_finite

#: matches per batched NCC call when ``NCCConfig.batch_size`` is None, per device type.
DEFAULT_BATCH_SIZE = {"cpu": 512, "cuda": 4096}
#: Upper bound of ``template_radius + search_radius`` (pixels): each match holds a
#: (2 (r_t + r_s) + 1)^2 window per perturbation (paper: 10 + 10); 1000 tried to allocate 320 GB.
MAX_WINDOW_RADIUS_PX = 64
#: Upper bound of ``NCCConfig.batch_size`` (matches per batched call).
MAX_NCC_BATCH = 65536


@dataclass(frozen=True, kw_only=True)
class NCCConfig:
    """Parameters of the pairwise NCC refinement (paper App. E).

    Defaults chosen by measurement (``benchmarks/bench_ncc.py``, Oxford graf and boat 1->2
    with GT patch homographies, SIFT and GFTT front ends): the 25 "paper" shapes and the
    5 "small" ones are never more accurate than "none" (e.g. graf SIFT 0.26 vs 0.24 px,
    graf GFTT 0.28 vs 0.22 px) and cost 2-4x more; the cornerness gate and ``min_gain`` > 0
    only lose good moves there; rejecting border peaks matters on ambiguous content (on the
    pycolmap synthetic scene it keeps the track-relative error at 1.9 px instead of 5.4 px);
    3 sub-pixel iterations bring the error on a known homography from 0.16 to 0.05 px.

    Track walk defaults chosen with ``benchmarks/bench_accuracy.py`` (GT track residual
    median, demo + Middlebury temple + Strecha fountain and entry, COLMAP default and
    permissive matching, change vs the input database): with the filter's planes and
    r = 10 the residual rose on the demo (+27%/+35%) and the temple (+39%/+57%); searching
    each match with both the filter's pair and a local affine pair (``rectification =
    "both"``) removes most of that (demo -54%/-47%); r = 6 is what keeps the temple from
    getting worse (r = 10: +9%/+32%, r = 6: -16%/-2%) at a cost of 2-10 points on the
    Strecha scenes (r = 6: -36% to -38%; r = 10: -38% to -48%), so the shipped NCC recipes
    set ``template_radius = 6``. The pairwise default stays at the paper's 10: with an exact
    homography (no relief) the larger template is the more precise (0.05 vs 0.10 px on
    Oxford graf with a known warp).

    Attributes:
        template_radius: r, half size of the template in pixels (paper: 10, 21x21 patch;
            the shipped NCC recipes use 6, 13x13: see below).
        search_radius: half size of the offset search in pixels (paper: 10).
        perturbations: which template shapes are tried on the extended pair: "none" (the
            pair itself), "paper" (App. E's A_{rho,f}: 5 rotations x 5 factors, applied to
            the template only; not the reference's 25 shapes, its own anisotropic scalings
            times rotations, through which it samples inversely) or "small" (identity,
            +-15 degrees, factors 5/6 and 6/5).
        use_base_pair: also try the base pair (identity / keypoint affine frame).
        ellipse_mask: NCC* - restrict the search to the structure-tensor ellipse. The
            tensor is taken from the (unperturbed) template; the semi-axis along the edge
            is ``search_radius * sqrt(lambda_min / lambda_max)`` floored at 0.5 px (the
            paper says about 1 px); with ``reject_border`` a peak held back by the mask (not
            a local maximum of the unmasked map) is rejected like a border peak.
        min_gain: a move of at least one pixel is applied only if it raises NCC by at least
            this much (NCC in [-1, 1]).
        min_ncc: a move is applied only if its NCC peak reaches this (in [-1, 1]; -1 = no
            floor): a weak peak is more likely wrong than right.
        reject_border: reject moves whose peak lies on the border of the search window (or
            is held back by the NCC* ellipse).
        cornerness_gate: skip edge-like patches (structure-tensor test).
        min_cornerness: threshold of the gate (lambda_min / lambda_max of the patch).
        min_template_std: templates whose intensity standard deviation is below this
            ([0, 1] intensity scale; uint8 images are divided by 255) are flat and never
            moved (NCC is undefined on them).
        move: which side may move, "1", "2" or "auto" (the paper's: the higher NCC moves).
        coarse_shapes: with several template shapes, choose the shape by NCC on a stride-2
            grid of offsets and search the full grid with that shape only (about 3x
            cheaper for "paper"; False evaluates every shape at every offset).
        subpixel_iterations: after the parabola fit on the integer NCC map, re-sample the
            window at the sub-pixel estimate and fit again on the 3x3 neighbourhood this many
            times (0 = the paper's single fit).
        batch_size: matches per batched call (bounds memory); None picks 512 on the CPU
            and 4096 on CUDA (``benchmarks/check_cuda.py`` on an H100: 2549 matches with
            the 25 shapes take 0.21 s in chunks of 512 and 0.05 s in chunks of 4096; on the
            CPU larger chunks gain nothing).
        device: "cpu", "cuda" or "auto" (the device of CUDA tensor inputs, else CUDA when
            torch sees one, else the CPU).
        rectification: the patch homography pairs of the track walk: "filter" (the
            filter's plane of each match), "local" (a local affine fit to the
            ``local_affine_neighbours`` nearest matches of its cluster, :mod:`.rectify`) or
            "both" (each match searched with both; the higher NCC peak wins).
        local_affine_neighbours: matches (the match included) of each local affine fit.
        check_radius: 0 (off), or the radius of a second template (another size than
            ``template_radius``): a move is applied only if the search with that template
            moves the same keypoint to within ``check_px`` pixels of it (both sizes agree;
            a peak biased by the patch's content rarely is at both sizes).
        check_px: agreement of the two template sizes, pixels.
        check_rule: "agree" (above) or "ncc": the ``check_radius`` template's move replaces
            the other where its NCC peak is higher by more than ``check_ncc_margin``.
        check_ncc_margin: NCC margin of the "ncc" rule.
        local_affine_max_residual_px: neighbours off the first local fit by more than this
            many pixels are dropped from the second.
        lsm: from the NCC peak (integer peak and parabola), align the fixed keypoint's
            template to the moving side by least-squares matching (:mod:`.lsm`: affine +
            gain/offset, bicubic samples, both patches in the match's common frame) and move
            the keypoint to LSM's position where it passes the three tests below; elsewhere
            the iterated parabolas (``subpixel_iterations``) refine the NCC peak as without
            LSM. Off by default (see ``recipes/mop_miho_lsm.toml``).
        lsm_radius: half size of the LSM template in pixels (0: ``template_radius``).
        lsm_radius_per_scale: 0 (off), or LSM templates sized by the fixed keypoint: radius
            ``round(lsm_radius_per_scale * scale)`` pixels, clamped to [4, the fixed radius
            above], where the keypoints carry an affine shape (scale = sqrt |det| of the
            frame; COLMAP's 4- and 6-column keypoints); the fixed radius elsewhere.
        lsm_affine: estimate the 4 affine terms (8 parameters); False: shift and
            radiometry only.
        lsm_max_iterations: Gauss-Newton steps at most; a match that has not converged
            by then keeps its NCC position.
        lsm_tol_px: a match's Gauss-Newton iteration has converged once its shift update
            is below this (common-frame pixels).
        lsm_max_shift_px: LSM's position is used only within this distance (max over x and
            y, common-frame pixels) of the NCC peak.
        lsm_max_sigma_px: ... and only if the a-posteriori standard deviation of its shift
            (largest semi-axis of the error ellipse, common-frame pixels) is below this.
    """

    template_radius: int = 10
    search_radius: int = 10
    perturbations: str = "none"
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
    device: str = "auto"
    rectification: str = "both"
    check_radius: int = 0
    check_px: float = 0.25
    check_rule: str = "agree"
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

    def __post_init__(self) -> None:
        object.__setattr__(self, "move", MoveSide.parse(self.move, "move"))
        require_finite(self)
        require_at_most("template_radius + search_radius", self.template_radius + self.search_radius,
                        MAX_WINDOW_RADIUS_PX, "the search window of every match is held in memory")
        require_at_most("batch_size", self.batch_size, MAX_NCC_BATCH, "matches held in memory at once")
        if self.template_radius < 1:
            raise ValueError(f"template_radius must be >= 1 pixel, got {self.template_radius}")
        if self.search_radius < 1:
            raise ValueError(f"search_radius must be >= 1 pixel, got {self.search_radius}")
        if self.perturbations not in ("none", "small", "paper"):
            raise ValueError(
                f"perturbations must be none, small or paper, got {self.perturbations!r}"
            )
        if self.min_gain < 0:
            raise ValueError(f"min_gain must be >= 0, got {self.min_gain}")
        if not -1 <= self.min_ncc <= 1:
            raise ValueError(f"min_ncc must be in [-1, 1], got {self.min_ncc}")
        if not 0 <= self.min_cornerness <= 1:
            raise ValueError(f"min_cornerness must be in [0, 1], got {self.min_cornerness}")
        if self.min_template_std < 0:
            raise ValueError(f"min_template_std must be >= 0, got {self.min_template_std}")
        if not 0 <= self.subpixel_iterations <= 10:
            raise ValueError(
                f"subpixel_iterations must be in [0, 10], got {self.subpixel_iterations}"
            )
        if self.batch_size is not None and self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.rectification not in ("filter", "local", "both"):
            raise ValueError(f"rectification must be filter, local or both, got "
                             f"{self.rectification!r}")
        if self.check_radius < 0 or self.check_radius == self.template_radius:
            raise ValueError(f"check_radius must be 0 (off) or >= 1 and not template_radius, "
                             f"got {self.check_radius}")
        if self.check_rule not in ("agree", "ncc"):
            raise ValueError(f"check_rule must be agree or ncc, got {self.check_rule!r}")
        if not 0 <= self.check_ncc_margin <= 2:
            raise ValueError(f"check_ncc_margin must be in [0, 2], got {self.check_ncc_margin}")
        if not self.check_px > 0:
            raise ValueError(f"check_px must be > 0 pixels, got {self.check_px}")
        if self.local_affine_neighbours < 6:
            raise ValueError(f"local_affine_neighbours must be >= 6, got "
                             f"{self.local_affine_neighbours}")
        if not self.local_affine_max_residual_px > 0:
            raise ValueError(f"local_affine_max_residual_px must be > 0, got "
                             f"{self.local_affine_max_residual_px}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")
        if not 0 <= self.lsm_radius <= MAX_WINDOW_RADIUS_PX:
            raise ValueError(f"lsm_radius must be in [0, {MAX_WINDOW_RADIUS_PX}] pixels "
                             f"(0: template_radius), got {self.lsm_radius}")
        if not self.lsm_radius_per_scale >= 0:
            raise ValueError(f"lsm_radius_per_scale must be >= 0 (0: off), got "
                             f"{self.lsm_radius_per_scale}")
        if not 1 <= self.lsm_max_iterations <= 50:
            raise ValueError(f"lsm_max_iterations must be in [1, 50], got {self.lsm_max_iterations}")
        if not 0 < self.lsm_tol_px <= 0.1:
            raise ValueError(f"lsm_tol_px must be in (0, 0.1] pixels, got {self.lsm_tol_px}")
        if not self.lsm_max_shift_px > 0:
            raise ValueError(f"lsm_max_shift_px must be > 0 pixels, got {self.lsm_max_shift_px}")
        if not self.lsm_max_sigma_px > 0:
            raise ValueError(f"lsm_max_sigma_px must be > 0 pixels, got {self.lsm_max_sigma_px}")


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
            its call); the batched walk is faster on the CPU too (fountain-P11, 113k matches:
            refine stage 13.6-15.9 s against 19.8-20.0 s with 2 workers, 21 s against 32 s
            with one; temple 2.0-2.5 s against 3.0-4.7 s). None (default): batched with the
            built-in refiner on every device; a custom ``refine_fn`` gets one call per pair.
    """

    max_images_in_memory: int = 8
    batch_pairs: bool | None = None
    duplicate_px: float = 1.0

    def __post_init__(self) -> None:
        if not self.duplicate_px >= 0:
            raise ValueError(f"duplicate_px must be >= 0 pixels, got {self.duplicate_px}")
        if self.max_images_in_memory < 2:
            raise ValueError(
                f"max_images_in_memory must be >= 2, got {self.max_images_in_memory}"
            )
