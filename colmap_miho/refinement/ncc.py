"""Pairwise NCC keypoint refinement on homography-rectified patches (paper Sec. 3.3, App. E).

``refine_pair`` refines N matches at once. For each match and each allowed direction the
template (radius r) is taken around the *fixed* keypoint and searched (radius s) around the
*moving* keypoint, both resampled into the common frame of the match's patch homography pair
``(A, B)`` (``A x1 ~ B x2``); :mod:`.search` does this for a whole chunk of matches at once
(search window sampled once per match and pass, only templates re-warped per shape, NCC maps
by grouped convolution). This module picks the direction per match, rejects doubtful moves,
refines the accepted ones to sub-pixel accuracy (:mod:`.subpixel`, on those matches only) and
maps them back: ``x_moving' = H_moving^-1 (H_moving x_moving + t)``.

Differences from the reference implementation (all configurable, see ``NCCConfig``):
- perturbations act on the template only and the window is sampled once per match; the
  reference, too, perturbs only the template, but re-samples the (unperturbed) window for
  every shape;
- a move is rejected when its peak lies on the border of the search window (or is held back
  by the NCC* mask) or when it raises NCC by less than ``min_gain``; the reference never
  rejects; so is a move whose peak NCC is below ``min_ncc``;
- flat templates (``min_template_std``) are never moved; an optional cornerness gate also
  skips edge-like ones;
- matches whose template or search window leaves the image are not refined.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..enums import MoveSide
from .config import DEFAULT_BATCH_SIZE, NCCConfig
from .lsm_step import LSM_COUNTERS, lsm_step
from .perturbations import perturbation_matrices
from .search import evaluate_direction, to_frame
from .subpixel import iterate_subpixel
from .warping import ImageStack, offset_grid, to_gray_tensor

logger = logging.getLogger(__name__)


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
        rejected: (N,) bool, a move was found but not applied (border or too small a gain).
        stats: counters (``n``, ``moved``, ``rejected_border``, ``rejected_gain``,
            ``rejected_weak`` (peak below ``min_ncc``), ``rejected_disagree`` (not
            confirmed by the ``check_radius`` template),
            ``gated_flat``, ``gated_edge``, ``outside``, ``invalid_homography``,
            ``seconds``, ``device``, ``shapes``; with ``config.lsm``, the counters of
            :data:`~.lsm_step.LSM_COUNTERS`: ``lsm_applied``, ``lsm_not_converged``,
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


def _as_array(name: str, value, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        tail = ", ".join(map(str, shape_tail))
        raise ValueError(f"{name} must have shape (N, {tail}), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} rows, expected {n}")
    return arr


def resolve_device(config: NCCConfig, *tensors) -> torch.device:
    """The torch device ``config.device`` means for inputs ``tensors`` (see NCCConfig)."""
    if config.device == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("config.device='cuda' but torch sees no CUDA device")
        return torch.device("cuda")
    if config.device == "auto":
        for t in tensors:
            if isinstance(t, ImageStack):
                return t.device  # built by the caller on the device it chose
            if isinstance(t, torch.Tensor) and t.is_cuda:
                return t.device
        if torch.cuda.is_available():
            return torch.device("cuda")
    return torch.device("cpu")


def _normalise_signs(homs: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Homographies are defined up to scale, sign included: flip each A (B) so that the
    homogeneous w of A x1 (B x2) is positive, as the patch sampling expects."""
    homs = homs.copy()
    for side, p in ((0, p1), (1, p2)):
        w = np.einsum("nj,nj->n", homs[:, side, 2, :2], p) + homs[:, side, 2, 2]
        homs[w < 0, side] *= -1.0
    return homs


def _base_pairs(n: int, affine1, affine2) -> np.ndarray:
    """(N, 2, 3, 3) base pair: identity, or the inverse keypoint affine frames scaled to keep
    about one common-frame pixel per image pixel."""
    base = np.tile(np.eye(3), (n, 2, 1, 1))
    if affine1 is None:
        return base
    det1 = np.abs(np.linalg.det(affine1))
    det2 = np.abs(np.linalg.det(affine2))
    ok = (det1 > 1e-12) & (det2 > 1e-12)
    scale = np.sqrt(np.sqrt(np.where(ok, det1 * det2, 1.0)))
    for side, aff in ((0, affine1), (1, affine2)):
        inv = np.linalg.inv(np.where(ok[:, None, None], aff, np.eye(2)))
        base[ok, side, :2, :2] = scale[ok, None, None] * inv[ok]
    return base


def refine_pair(
    image1,
    image2,
    pts1,
    pts2,
    patch_homographies,
    *,
    move: str | MoveSide | None = None,
    config: NCCConfig | None = None,
    affine1=None,
    affine2=None,
    progress: bool = False,
) -> RefineResult:
    """Refine N matches by NCC template matching on rectified patches.

    Args:
        image1, image2: grayscale images (H, W), numpy or torch, uint8 (scaled to [0, 1]) or
            float (intensities nominally in [0, 1]); or :class:`~.warping.ImageStack` objects
            with one image per match (several image pairs in one call).
        pts1, pts2: (N, 2) pixel coordinates (x, y), integer = pixel centre.
        patch_homographies: (N, 2, 3, 3) one pair (A, B) per match mapping image 1 and image 2
            into a common frame, ``A x1 ~ B x2`` (e.g. (I, H_2from1^-1) for MOP, the two
            middle homographies for MiHo); or (N, P, 2, 3, 3) P candidate pairs per match
            (the first with the template shapes of ``perturbations``, the others
            unperturbed; the best NCC peak over all of them wins).
        move: "1" or "2" (only that side may move, the other gives the template) or "auto"
            (both directions are tried, the one with the higher NCC peak moves: the paper's
            behaviour); ``None`` uses ``config.move``.
        config: :class:`NCCConfig` (defaults when None).
        affine1, affine2: optional (N, 2, 2) keypoint affine frames (columns = local axes in
            pixels) for the base pass; identity when omitted.
        progress: show a tqdm bar over chunks.

    Returns:
        :class:`RefineResult`. A match that cannot be refined (patch outside the image,
        singular homography, flat template) is returned unchanged and counted in ``stats``.
        On the CPU each match's outputs are bitwise the same whatever the other matches of
        the call (how many, their order, their images in an ImageStack), ``batch_size`` and
        torch's thread count (tests/refinement/test_ncc_batch_invariance.py); on CUDA they
        agree to float32 rounding.

    Raises:
        ValueError: on malformed inputs (shapes, dtypes, device).
    """
    t0 = time.perf_counter()
    cfg = config if config is not None else NCCConfig()
    side = MoveSide.parse(cfg.move if move is None else move, "move")
    p1 = _as_array("pts1", pts1, (2,), None)
    n = p1.shape[0]
    p2 = _as_array("pts2", pts2, (2,), n)
    homs = patch_homographies
    if isinstance(homs, torch.Tensor):
        homs = homs.detach().cpu().numpy()
    homs = np.asarray(homs, dtype=np.float64)
    extra = []
    if homs.ndim == 5:  # (N, P, 2, 3, 3): P candidate pairs per match
        extra = [_normalise_signs(_as_array("patch_homographies[:, k]", homs[:, k], (2, 3, 3), n),
                                  p1, p2) for k in range(1, homs.shape[1])]
        homs = homs[:, 0]
    homs = _as_array("patch_homographies", homs, (2, 3, 3), n)
    if (affine1 is None) != (affine2 is None):
        raise ValueError("affine1 and affine2 must be given together")
    if affine1 is not None:
        affine1 = _as_array("affine1", affine1, (2, 2), n)
        affine2 = _as_array("affine2", affine2, (2, 2), n)
    homs = _normalise_signs(homs, p1, p2)
    # keypoint scales (pixels) of each side, for LSM templates sized by the keypoint
    kp_scales = None
    if affine1 is not None and cfg.lsm and cfg.lsm_radius_per_scale > 0:
        kp_scales = tuple(np.sqrt(np.abs(np.linalg.det(a))) for a in (affine1, affine2))
    device = resolve_device(cfg, image1, image2, pts1, patch_homographies)
    img = (to_gray_tensor(image1, device), to_gray_tensor(image2, device))

    out1, out2 = p1.copy(), p2.copy()
    before = np.full(n, np.nan)
    after = np.full(n, np.nan)
    moved = np.zeros(n, np.int8)
    disp = np.zeros(n)
    rejected = np.zeros(n, bool)
    counts: dict[str, int | float | str] = dict.fromkeys(
        ["moved", "rejected_border", "rejected_gain", "rejected_weak", "gated_flat", "gated_edge", "outside",
         "invalid_homography"], 0)
    if cfg.lsm:
        counts.update(dict.fromkeys(LSM_COUNTERS, 0))

    shapes = torch.as_tensor(perturbation_matrices(cfg.perturbations), device=device)
    grid_t = offset_grid(cfg.template_radius, device)
    tpl_off = grid_t[None] @ shapes.transpose(1, 2)  # (K, P, 2): M w
    grid_c = 2.0 * offset_grid(cfg.template_radius // 2, device)  # every 2 px
    tpl_off_coarse = grid_c[None] @ shapes.transpose(1, 2)
    win_off = offset_grid(cfg.template_radius + cfg.search_radius, device)
    base = _base_pairs(n, affine1, affine2)
    use_base = cfg.use_base_pair and not (
        affine1 is None and np.allclose(homs, np.eye(3), atol=1e-12)
    )
    directions = {MoveSide.SECOND: [(0, 1)], MoveSide.FIRST: [(1, 0)]}.get(side, [(0, 1), (1, 0)])

    batch = cfg.batch_size or DEFAULT_BATCH_SIZE.get(device.type, 512)
    chunks = range(0, n, batch)
    if progress:
        from tqdm import tqdm

        chunks = tqdm(chunks, desc="NCC", unit="chunk")
    with torch.no_grad():
        for start in chunks:
            sl = slice(start, min(start + batch, n))
            x = (torch.as_tensor(p1[sl], device=device), torch.as_tensor(p2[sl], device=device))
            H_ext = torch.as_tensor(homs[sl], device=device)
            pairs: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = [
                (H_ext, tpl_off, tpl_off_coarse)]
            pairs += [(torch.as_tensor(h[sl], device=device), grid_t[None], None) for h in extra]
            if use_base:
                pairs.append((torch.as_tensor(base[sl], device=device), grid_t[None], None))
            cimg = tuple(im.rows(sl) if isinstance(im, ImageStack) else im for im in img)
            res = [
                (f, m, evaluate_direction(cimg[f], cimg[m], x[f], x[m], pairs, f, m, win_off, cfg))
                for f, m in directions
            ]
            _decide(res, cimg, sl, cfg, (out1, out2), before, after, moved, disp, rejected,
                    counts, kp_scales)

    if cfg.check_radius and moved.any():
        _check_agreement(image1, image2, p1, p2, patch_homographies, side, cfg, affine1, affine2,
                         (out1, out2), after, before, moved, disp, rejected, counts)
    counts.update(
        n=n,
        seconds=time.perf_counter() - t0,
        device=str(device),
        shapes=int(shapes.shape[0]) + len(extra) + int(use_base),
        directions=len(directions),
    )
    logger.debug("refine_pair: %s", counts)
    return RefineResult(
        pts1=out1, pts2=out2, ncc_before=before, ncc_after=after, moved_side=moved,
        displacement=disp, rejected=rejected, stats=counts,
    )


def _check_agreement(image1, image2, p1, p2, homs, side, cfg, affine1, affine2, outs, after,
                     before, moved, disp, rejected, counts) -> None:
    """Undo the moves that a second search with a ``check_radius`` template does not confirm
    (other side moved, or the two positions more than ``check_px`` apart)."""
    rows = np.flatnonzero(moved > 0)
    sub = torch.as_tensor(rows) if isinstance(image1, ImageStack) else None
    def pick(im):
        return im.rows(sub.to(im.device)) if isinstance(im, ImageStack) and sub is not None else im

    homs = homs.detach().cpu().numpy() if isinstance(homs, torch.Tensor) else np.asarray(homs)
    chk = refine_pair(
        pick(image1), pick(image2), p1[rows], p2[rows], homs[rows], move=side,
        config=replace(cfg, template_radius=cfg.check_radius, check_radius=0),
        affine1=None if affine1 is None else affine1[rows],
        affine2=None if affine2 is None else affine2[rows])
    m = moved[rows]
    if cfg.check_rule == "ncc":
        # the smaller template wins where the larger one correlates clearly worse: the
        # larger one then spans what the rectification does not model (relief, occlusion)
        swap = (chk.moved_side == m) & (chk.ncc_after > after[rows] + cfg.check_ncc_margin)
        sel = rows[swap]
        for side_out, chk_pts in ((outs[0], chk.pts1), (outs[1], chk.pts2)):
            side_out[sel] = chk_pts[swap]
        disp[sel] = chk.displacement[swap]
        after[sel] = chk.ncc_after[swap]
        counts["smaller_template"] = int(sel.size)
        return
    mine = np.where((m == 1)[:, None], outs[0][rows], outs[1][rows])
    theirs = np.where((m == 1)[:, None], chk.pts1, chk.pts2)
    agree = (chk.moved_side == m) & (np.linalg.norm(mine - theirs, axis=1) <= cfg.check_px)
    undo = rows[~agree]
    outs[0][undo] = p1[undo]
    outs[1][undo] = p2[undo]
    moved[undo] = 0
    disp[undo] = 0.0
    rejected[undo] = True
    after[undo] = before[undo]
    counts["moved"] -= int(undo.size)
    counts["rejected_disagree"] = int(undo.size)


def _decide(res, img, sl, cfg, outs, before, after, moved, disp, rejected, counts,
            kp_scales=None) -> None:
    """Choose the direction per match, reject or accept its move, and refine the accepted
    moves to sub-pixel accuracy (only those: the losing direction needs no sub-pixel step).
    Writes into the output arrays."""
    cand = []
    for f, m, r in res:
        host = {k: r[k].cpu().numpy() for k in
                ("peak", "centre", "border", "zero", "inside", "valid", "flat", "edge")}
        usable = host["valid"] & host["inside"] & ~host["flat"]
        if cfg.cornerness_gate:
            usable &= ~host["edge"]
        cand.append((f, m, r, host, usable))
    score = np.stack([np.where(u, h["peak"], -np.inf) for *_, h, u in cand])
    best = score.argmax(axis=0)
    idx = np.arange(sl.start, sl.stop)
    none = ~np.stack([u for *_, u in cand]).any(axis=0)
    h0 = cand[0][3]  # count why nothing could be used, once per match
    counts["invalid_homography"] += int((none & ~h0["valid"]).sum())
    counts["outside"] += int((none & h0["valid"] & ~h0["inside"]).sum())
    counts["gated_flat"] += int((none & h0["valid"] & h0["inside"] & h0["flat"]).sum())
    counts["gated_edge"] += int(
        (none & h0["valid"] & h0["inside"] & ~h0["flat"] & h0["edge"]).sum()
    )
    for d, (f, m, r, h, usable) in enumerate(cand):
        rows = (best == d) & usable
        gi = idx[rows]
        before[gi] = h["centre"][rows]
        after[gi] = h["centre"][rows]
        on_border = h["border"][rows] & cfg.reject_border
        small_gain = ~h["zero"][rows] & (h["peak"][rows] - h["centre"][rows] < cfg.min_gain)
        weak = ~h["zero"][rows] & (h["peak"][rows] < cfg.min_ncc)
        reject = on_border | small_gain | weak
        counts["rejected_border"] += int(on_border.sum())
        counts["rejected_gain"] += int((small_gain & ~on_border).sum())
        counts["rejected_weak"] += int((weak & ~small_gain & ~on_border).sum())
        rejected[gi[reject]] = True
        take = np.flatnonzero(rows)[~reject]
        if take.size == 0:
            continue
        sel = torch.as_tensor(take, device=r["offset"].device)
        H_inv, frame = r["H_inv"][sel], r["frame_m"][sel]
        img_m = img[m].rows(sel) if isinstance(img[m], ImageStack) else img[m]
        off = r["offset"][sel]
        todo = None  # the matches that get the iterated parabolas: all without LSM
        if cfg.lsm:
            # LSM starts from the NCC peak's parabola; the matches it does not accept get
            # the iterated parabolas, as without LSM
            img_f = img[f].rows(sel) if isinstance(img[f], ImageStack) else img[f]
            scale_f = None if kp_scales is None else kp_scales[f][idx[take]]
            off, lsm_counts, accepted = lsm_step(img_f, img_m, r["H_f_inv"][sel],
                                                 r["frame_f"][sel], H_inv, frame, off, cfg,
                                                 scale_f)
            for key, value in lsm_counts.items():
                counts[key] = counts.get(key, 0) + value
            todo = torch.nonzero(~accepted)[:, 0]
        if todo is None:
            off = iterate_subpixel(img_m, H_inv, frame, off, r["template"][sel],
                                   cfg.template_radius, cfg.subpixel_iterations)
        elif todo.numel():
            img_t = img_m.rows(todo) if isinstance(img_m, ImageStack) else img_m
            off[todo] = iterate_subpixel(img_t, H_inv[todo], frame[todo], off[todo],
                                         r["template"][sel][todo], cfg.template_radius,
                                         cfg.subpixel_iterations)
        new = to_frame(H_inv, frame + off).cpu().numpy()
        ok = idx[take]
        old = outs[m][ok]
        outs[m][ok] = new
        disp[ok] = np.linalg.norm(new - old, axis=1)
        moved[ok] = m + 1
        after[ok] = h["peak"][take]
        counts["moved"] += int(ok.size)
