"""Pairwise NCC keypoint refinement on homography-rectified patches (paper Sec. 3.3, App. E).

A template around the fixed keypoint is searched around the moving one, both resampled into the
common frame of the match's patch homography pair ``(A, B)`` (``A x1 ~ B x2``); the move maps back
as ``x' = H^-1 (H x + t)``. Unlike the reference: the window is sampled once per match; moves with a
peak on the window's border or below ``min_ncc`` are rejected; flat templates and patches leaving
the image are not moved."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import torch

from .. import devices
from ..enums import MoveSide
from ..errors import InvalidInput
from .config import DEFAULT_BATCH_SIZE, NCCConfig
from .lsm.step import LSM_COUNTERS, lsm_step
from .ncc.perturbations import perturbation_matrices
from .ncc.search import Pass, evaluate_direction
from .ncc.subpixel import iterate_subpixel
from .warping import ImageStack, job_images, offset_grid, to_frame, to_gray_tensor

logger = logging.getLogger(__name__)

#: an image argument of :func:`refine_pair`: (H, W) numpy or torch, or one image per match.
ImageInput = np.ndarray | torch.Tensor | ImageStack
#: an array argument: numpy, torch or anything ``np.asarray`` takes.
ArrayInput = np.ndarray | torch.Tensor


@dataclass(frozen=True)
class RefineResult:
    """Output of :func:`refine_pair` (N = number of matches).

    Attributes:
        pts1, pts2: (N, 2) float64 refined pixel coordinates (integer = pixel centre); at most
            one of the two differs from the input per match.
        ncc_before: (N,) float64 NCC in [-1, 1] at zero offset (best shape) of the chosen
            direction; NaN where the match was not evaluated.
        ncc_after: (N,) float64 NCC of the applied move (= ncc_before where nothing moved).
        moved_side: (N,) int8, 0 none, 1 or 2.
        displacement: (N,) float64 pixels the moved keypoint travelled (0 where none).
        rejected: (N,) bool, a move was found but not applied (border or too weak a peak).
        ncc_second: (N,) float64 NCC of the best separated peak of the applied move's map
            (:func:`.ncc.correlation.find_peaks`' ``second``), NaN where nothing moved; how
            distinct the peak taken is. None from refiners that do not report it.
        stats: counters (``n``, ``moved``, ``rejected_border``,
            ``rejected_weak`` (peak below ``min_ncc``), ``gated_flat``, ``outside``,
            ``invalid_homography``,
            ``seconds``, ``device``, ``shapes``; with ``config.lsm.enabled``, the counters of
            :data:`~.lsm.step.LSM_COUNTERS`: ``lsm_applied``, ``lsm_not_converged``,
            ``lsm_far``, ``lsm_imprecise``).
    """

    pts1: np.ndarray
    pts2: np.ndarray
    ncc_before: np.ndarray
    ncc_after: np.ndarray
    moved_side: np.ndarray
    displacement: np.ndarray
    rejected: np.ndarray
    stats: dict = field(default_factory=dict)
    ncc_second: np.ndarray | None = None


def resolve_device(config: NCCConfig, *inputs: object) -> torch.device:
    """The torch device ``config.device`` means; "auto" keeps the device of the first stack or CUDA tensor."""
    inputs_on = None
    for t in inputs:
        if isinstance(t, ImageStack) or (isinstance(t, torch.Tensor) and t.is_cuda):
            inputs_on = t.device
            break
    return devices.resolve_device(config.device, inputs_on)


@dataclass
class _Outputs:
    """The arrays :func:`refine_pair` fills in (N rows, see :class:`RefineResult`) and its
    counters."""

    pts: tuple[np.ndarray, np.ndarray]
    before: np.ndarray
    after: np.ndarray
    moved: np.ndarray
    disp: np.ndarray
    rejected: np.ndarray
    second: np.ndarray
    counts: dict[str, int | float | str]

    @classmethod
    def unchanged(cls, p1: np.ndarray, p2: np.ndarray) -> _Outputs:
        n = p1.shape[0]
        counts: dict[str, int | float | str] = dict.fromkeys(
            ["moved", "rejected_border", "rejected_weak", "gated_flat",
             "outside", "invalid_homography"], 0)
        return cls(pts=(p1.copy(), p2.copy()), before=np.full(n, np.nan), after=np.full(n, np.nan),
                   moved=np.zeros(n, np.int8), disp=np.zeros(n), rejected=np.zeros(n, bool),
                   second=np.full(n, np.nan), counts=counts)

    def add(self, key: str, value: int) -> None:
        count = self.counts[key]
        assert isinstance(count, int)
        self.counts[key] = count + value


@dataclass(frozen=True)
class _Offsets:
    """Sample offsets of one :func:`refine_pair` call, on its device."""

    shapes: torch.Tensor  # (K, 2, 2) template shapes M
    grid_t: torch.Tensor  # (P, 2) template pixels, radius r
    tpl: torch.Tensor  # (K, P, 2) M w
    tpl_coarse: torch.Tensor  # (K, Pc, 2) the same every 2 px
    win: torch.Tensor  # (Pw, 2) search window, radius r + s

    @classmethod
    def of(cls, cfg: NCCConfig, device: torch.device) -> _Offsets:
        shapes = torch.as_tensor(perturbation_matrices(cfg.perturbations), device=device)
        grid_t = offset_grid(cfg.template_radius, device)
        grid_c = 2.0 * offset_grid(cfg.template_radius // 2, device)  # every 2 px
        return cls(shapes=shapes, grid_t=grid_t, tpl=grid_t[None] @ shapes.transpose(1, 2),
                   tpl_coarse=grid_c[None] @ shapes.transpose(1, 2),
                   win=offset_grid(cfg.template_radius + cfg.search_radius, device))


def refine_pair(
    image1: ImageInput,
    image2: ImageInput,
    pts1: ArrayInput,
    pts2: ArrayInput,
    patch_homographies: ArrayInput,
    *,
    move: str | MoveSide | None = None,
    config: NCCConfig | None = None,
    affine1: ArrayInput | None = None,
    affine2: ArrayInput | None = None,
    progress: bool = False,
) -> RefineResult:
    # over 80 lines only by its docstring (the public entry point's inputs and guarantees)
    """Refine N matches by NCC template matching on rectified patches.

    Args:
        image1, image2: gray ``(H, W)`` numpy or torch, uint8 or float in [0, 1]; or
          :class:`~.warping.ImageStack` with one image per match.
        pts1, pts2: ``(N, 2)`` pixels (x, y), integer = pixel centre.
        patch_homographies: ``(N, 2, 3, 3)`` pairs ``(A, B)`` with ``A x1 ~ B x2``, or
          ``(N, P, 2, 3, 3)`` candidates (the best peak wins).
        move: "1", "2" or "auto" (the side with the higher peak moves); None uses ``config.move``.
        config: :class:`NCCConfig`; None: the paper's pairwise values.
        affine1, affine2: optional ``(N, 2, 2)`` keypoint affine frames for the base pass.

    Returns a :class:`RefineResult`; matches that cannot be refined come back unchanged. On the CPU
    a match's outputs do not depend on the other matches or the batch size. ValueError on malformed
    input."""
    t0 = time.perf_counter()
    if config is not None and not isinstance(config, NCCConfig):
        raise InvalidInput(f"config must be an NCCConfig, got {type(config).__name__}")
    cfg = config if config is not None else NCCConfig.pairwise()
    side = MoveSide.parse(cfg.move if move is None else move, "move")
    inp = pair_inputs(pts1, pts2, patch_homographies, affine1, affine2)
    n = inp.p1.shape[0]
    device = resolve_device(cfg, image1, image2, pts1, patch_homographies)
    img = (to_gray_tensor(image1, device), to_gray_tensor(image2, device))
    out = _Outputs.unchanged(inp.p1, inp.p2)
    if cfg.lsm.enabled:
        out.counts.update(dict.fromkeys(LSM_COUNTERS, 0))
    offs = _Offsets.of(cfg, device)
    base = base_pairs(n, inp.affine1, inp.affine2)
    use_base = cfg.use_base_pair and not (
        inp.affine1 is None and np.allclose(inp.homs, np.eye(3), atol=1e-12)
    )
    directions = {MoveSide.SECOND: [(0, 1)], MoveSide.FIRST: [(1, 0)]}.get(side, [(0, 1), (1, 0)])

    batch = cfg.batch_size or DEFAULT_BATCH_SIZE.get(device.type, 512)
    chunks: Iterable[int] = range(0, n, batch)
    if progress:
        from tqdm import tqdm

        chunks = tqdm(chunks, desc="NCC", unit="chunk")
    with torch.no_grad():
        for start in chunks:
            sl = slice(start, min(start + batch, n))
            x = (torch.as_tensor(inp.p1[sl], device=device),
                 torch.as_tensor(inp.p2[sl], device=device))
            passes: list[Pass] = [(torch.as_tensor(inp.homs[sl], device=device), offs.tpl,
                                   offs.tpl_coarse)]
            passes += [(torch.as_tensor(h[sl], device=device), offs.grid_t[None], None)
                       for h in inp.extra]
            if use_base:
                passes.append((torch.as_tensor(base[sl], device=device), offs.grid_t[None], None))
            cimg = (job_images(img[0], sl), job_images(img[1], sl))
            res = [
                (f, m, evaluate_direction(cimg[f], cimg[m], x[f], x[m], passes, f, m, offs.win, cfg))
                for f, m in directions
            ]
            _decide(res, cimg, sl, cfg, out)

    out.counts.update(
        n=n,
        seconds=time.perf_counter() - t0,
        device=str(device),
        shapes=int(offs.shapes.shape[0]) + len(inp.extra) + int(use_base),
        directions=len(directions),
    )
    logger.debug("refine_pair: %s", out.counts)
    return RefineResult(
        pts1=out.pts[0], pts2=out.pts[1], ncc_before=out.before, ncc_after=out.after,
        moved_side=out.moved, displacement=out.disp, rejected=out.rejected, stats=out.counts,
        ncc_second=out.second,
    )


#: one direction's search: (fixed side, moving side, :func:`.ncc.search.evaluate_direction`'s dict).
Direction = tuple[int, int, dict[str, torch.Tensor]]


def _subpixel(img: tuple[torch.Tensor | ImageStack, torch.Tensor | ImageStack], direction: tuple[int, int],
              r: dict[str, torch.Tensor], rows: tuple[torch.Tensor, np.ndarray], cfg: NCCConfig,
              out: _Outputs) -> torch.Tensor:
    """Sub-pixel offsets (J, 2) of the accepted moves of ``direction`` (fixed ``f``, moving
    ``m``), ``rows`` = (their rows in the chunk, their match indices): least-squares matching
    from the NCC peak's parabola where ``cfg.lsm.enabled`` and it passes its tests, the iterated
    parabolas elsewhere (all of them without LSM)."""
    (f, m), (sel, _) = direction, rows
    H_inv, frame, off = r["H_inv"][sel], r["frame_m"][sel], r["offset"][sel]
    img_m = job_images(img[m], sel)
    if not cfg.lsm.enabled:
        return iterate_subpixel(img_m, H_inv, frame, off, r["template"][sel], cfg.template_radius,
                                cfg.subpixel_iterations)
    off, lsm_counts, accepted = lsm_step(job_images(img[f], sel), img_m, r["H_f_inv"][sel], r["frame_f"][sel],
                                         H_inv, frame, off, cfg)
    for key, value in lsm_counts.items():
        out.add(key, int(value))
    todo = torch.nonzero(~accepted)[:, 0]
    if todo.numel():
        off[todo] = iterate_subpixel(job_images(img_m, todo), H_inv[todo], frame[todo], off[todo],
                                     r["template"][sel][todo], cfg.template_radius, cfg.subpixel_iterations)
    return off


def _decide(res: list[Direction], img: tuple[torch.Tensor | ImageStack, torch.Tensor | ImageStack],
            sl: slice, cfg: NCCConfig, out: _Outputs) -> None:
    """Choose each match's direction, accept or reject its move, and refine accepted ones to sub-pixel."""
    cand = []
    for f, m, r in res:
        host = {k: r[k].cpu().numpy() for k in
                ("peak", "centre", "border", "zero", "inside", "valid", "flat")}
        usable = host["valid"] & host["inside"] & ~host["flat"]
        cand.append((f, m, r, host, usable))
    score = np.stack([np.where(u, h["peak"], -np.inf) for *_, h, u in cand])
    best = score.argmax(axis=0)
    idx = np.arange(sl.start, sl.stop)
    none = ~np.stack([u for *_, u in cand]).any(axis=0)
    h0 = cand[0][3]  # count why nothing could be used, once per match
    out.add("invalid_homography", int((none & ~h0["valid"]).sum()))
    out.add("outside", int((none & h0["valid"] & ~h0["inside"]).sum()))
    out.add("gated_flat", int((none & h0["valid"] & h0["inside"] & h0["flat"]).sum()))
    for d, (f, m, r, h, usable) in enumerate(cand):
        rows = (best == d) & usable
        gi = idx[rows]
        out.before[gi] = h["centre"][rows]
        out.after[gi] = h["centre"][rows]
        on_border = h["border"][rows] & cfg.reject_border
        weak = ~h["zero"][rows] & (h["peak"][rows] < cfg.min_ncc)
        reject = on_border | weak
        out.add("rejected_border", int(on_border.sum()))
        out.add("rejected_weak", int((weak & ~on_border).sum()))
        out.rejected[gi[reject]] = True
        take = np.flatnonzero(rows)[~reject]
        if take.size == 0:
            continue
        sel = torch.as_tensor(take, device=r["offset"].device)
        H_inv, frame = r["H_inv"][sel], r["frame_m"][sel]
        off = _subpixel(img, (f, m), r, (sel, idx[take]), cfg, out)
        new = to_frame(H_inv, frame + off).cpu().numpy()
        ok = idx[take]
        old = out.pts[m][ok]
        out.pts[m][ok] = new
        out.disp[ok] = np.linalg.norm(new - old, axis=1)
        out.moved[ok] = m + 1
        out.after[ok] = h["peak"][take]
        out.second[ok] = r["second"][sel].cpu().numpy()
        out.add("moved", int(ok.size))


# the array inputs of refine_pair: shape checks, float64 numpy, and the homography pairs it
# searches (the filter's, oriented; the keypoint-frame base pair)


def _as_array(name: str, value: object, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    tail = ", ".join(map(str, shape_tail))
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInput(f"{name} must be a numeric array of shape (N, {tail}), got {type(value).__name__}") from None
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise InvalidInput(f"{name} must have shape (N, {tail}), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise InvalidInput(f"{name} has {arr.shape[0]} rows, expected {n}")
    if not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1))[0])
        raise InvalidInput(f"{name} holds NaN or inf (row {bad} first)")
    return arr


def normalise_signs(homs: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Flip each A (B) so that w of A x1 (B x2) is positive, as the patch sampling expects."""
    homs = homs.copy()
    for side, p in ((0, p1), (1, p2)):
        w = np.einsum("nj,nj->n", homs[:, side, 2, :2], p) + homs[:, side, 2, 2]
        homs[w < 0, side] *= -1.0
    return homs


def base_pairs(n: int, affine1: np.ndarray | None, affine2: np.ndarray | None) -> np.ndarray:
    """``(N, 2, 3, 3)`` base pair: identity, or inverse affine frames scaled to ~1 frame px per image px."""
    base = np.tile(np.eye(3), (n, 2, 1, 1))
    if affine1 is None or affine2 is None:
        return base
    det1 = np.abs(np.linalg.det(affine1))
    det2 = np.abs(np.linalg.det(affine2))
    ok = (det1 > 1e-12) & (det2 > 1e-12)
    scale = np.sqrt(np.sqrt(np.where(ok, det1 * det2, 1.0)))
    for side, aff in ((0, affine1), (1, affine2)):
        inv = np.linalg.inv(np.where(ok[:, None, None], aff, np.eye(2)))
        base[ok, side, :2, :2] = scale[ok, None, None] * inv[ok]
    return base


@dataclass
class PairInputs:
    """:func:`refine_pair`'s inputs as float64 numpy arrays (N matches)."""

    p1: np.ndarray  # (N, 2)
    p2: np.ndarray  # (N, 2)
    homs: np.ndarray  # (N, 2, 3, 3) first pair, signs normalised
    extra: list[np.ndarray]  # further (N, 2, 3, 3) candidate pairs, signs normalised
    affine1: np.ndarray | None  # (N, 2, 2)
    affine2: np.ndarray | None


def pair_inputs(pts1: ArrayInput, pts2: ArrayInput, patch_homographies: ArrayInput,
            affine1: ArrayInput | None, affine2: ArrayInput | None) -> PairInputs:
    """Check the shapes of :func:`refine_pair`'s arrays and convert them (``ValueError``)."""
    p1 = _as_array("pts1", pts1, (2,), None)
    n = p1.shape[0]
    p2 = _as_array("pts2", pts2, (2,), n)
    homs = patch_homographies
    if isinstance(homs, torch.Tensor):
        homs = homs.detach().cpu().numpy()
    homs = np.asarray(homs, dtype=np.float64)
    extra = []
    if homs.ndim == 5:  # (N, P, 2, 3, 3): P candidate pairs per match
        extra = [normalise_signs(_as_array("patch_homographies[:, k]", homs[:, k], (2, 3, 3), n),
                                  p1, p2) for k in range(1, homs.shape[1])]
        homs = homs[:, 0]
    homs = _as_array("patch_homographies", homs, (2, 3, 3), n)
    if (affine1 is None) != (affine2 is None):
        raise ValueError("affine1 and affine2 must be given together")
    a1 = a2 = None
    if affine1 is not None:
        a1 = _as_array("affine1", affine1, (2, 2), n)
        a2 = _as_array("affine2", affine2, (2, 2), n)
    return PairInputs(p1, p2, normalise_signs(homs, p1, p2), extra, a1, a2)
