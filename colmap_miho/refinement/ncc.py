"""Pairwise NCC keypoint refinement on homography-rectified patches (paper Sec. 3.3, App. E).

``refine_pair`` refines N matches at once. For each match and each allowed direction the
template (radius r) is taken around the *fixed* keypoint and searched (radius s) around the
*moving* keypoint, both resampled into the common frame of the match's patch homography pair
``(A, B)`` (``A x1 ~ B x2``). The search window is sampled once per match and pass; only the
template is re-warped per shape perturbation; all NCC maps of a chunk come from one grouped
convolution. The best shape and integer offset are refined by separate 1-D parabolas in x and
y, and mapped back: ``x_moving' = H_moving^-1 (H_moving x_moving + t)``.

Differences from the reference implementation (all configurable, see ``NCCConfig``):
- perturbations act on the template only (the window is not re-sampled per shape); the
  reference also perturbs the window side, which is close to the inverse template shape;
- a move is rejected when its peak lies on the border of the search window (or is held back
  by the NCC* mask) or when it raises NCC by less than ``min_gain``; the reference never
  rejects;
- flat templates (``min_template_std``) are never moved; an optional cornerness gate also
  skips edge-like ones;
- matches whose template or search window leaves the image are not refined.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..enums import MoveSide
from .config import NCCConfig
from .correlation import (
    MIN_CURVATURE,
    ellipse_masks,
    find_peaks,
    ncc_maps,
    structure_tensor,
)
from .perturbations import perturbation_matrices
from .warping import invert_homographies, offset_grid, sample_patches, to_gray_tensor

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
            ``gated_flat``, ``gated_edge``, ``outside``, ``invalid_homography``,
            ``seconds``, ``device``, ``shapes``).
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


def _pick_device(config: NCCConfig, *tensors) -> torch.device:
    if config.device == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("config.device='cuda' but torch sees no CUDA device")
        return torch.device("cuda")
    if config.device == "auto":
        for t in tensors:
            if isinstance(t, torch.Tensor) and t.is_cuda:
                return t.device
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


def _run_direction(img_f, img_m, x_f, x_m, pairs, f, m, tpl_off, win_off, cfg):
    """Evaluate one direction (template from side f, search in side m) for a chunk.

    pairs: list of (H (J, 2, 3, 3) float64 tensor, template offsets (K, P, 2), the same
    shapes sampled every 2 px (K, Pc, 2) or None), one entry per pass (extended, base).
    Returns a dict of (J,) tensors.
    """
    maps, inside_all, valid_all, pass_of_k, k_local = [], [], [], [], []
    first_template = None
    H_m_invs, c_ms, templates = [], [], []
    st = 2 * cfg.template_radius + 1
    sw = 2 * (cfg.template_radius + cfg.search_radius) + 1
    for p, (H, offs, offs_coarse) in enumerate(pairs):
        H_f, H_m = H[:, f], H[:, m]
        H_f_inv, ok_f = invert_homographies(H_f)
        H_m_inv, ok_m = invert_homographies(H_m)
        c_f = (H_f[:, :2, :2] @ x_f[:, :, None])[..., 0] + H_f[:, :2, 2]
        c_f = c_f / ((H_f[:, 2:, :2] @ x_f[:, :, None])[..., 0] + H_f[:, 2:, 2]).clamp_min(1e-12)
        c_m = (H_m[:, :2, :2] @ x_m[:, :, None])[..., 0] + H_m[:, :2, 2]
        c_m = c_m / ((H_m[:, 2:, :2] @ x_m[:, :, None])[..., 0] + H_m[:, 2:, 2]).clamp_min(1e-12)
        win, in_w = sample_patches(img_m, H_m_inv, c_m, win_off[None])
        J = c_f.shape[0]
        win = win.reshape(J, sw, sw)
        if offs.shape[0] > 1 and cfg.coarse_shapes:
            # choose the shape with templates sampled every 2 px against the window's even
            # pixels (offsets on a stride-2 grid), then sample and search the chosen shape
            # at full resolution: the cost of the shapes drops ~4x in samples and ~10x in MACs
            tpl_c, in_t = sample_patches(img_f, H_f_inv, c_f, offs_coarse)
            sc = int(round(offs_coarse.shape[1] ** 0.5))
            coarse = ncc_maps(win[:, ::2, ::2], tpl_c.reshape(J, -1, sc, sc))
            best = coarse.reshape(J, offs.shape[0], -1).amax(dim=-1).argmax(dim=1)
            ident, in_i = sample_patches(img_f, H_f_inv, c_f, offs[:1])
            in_t = in_t & in_i
            chosen = ident.clone()
            for k in torch.unique(best).tolist():
                if k:
                    sel = torch.nonzero(best == k)[:, 0]
                    tk, _ = sample_patches(img_f, H_f_inv[sel], c_f[sel], offs[k : k + 1])
                    chosen[sel] = tk
            # the unperturbed shape always competes at full resolution too: the coarse
            # choice is blurred by aliasing
            tpl = torch.cat([ident, chosen], dim=1).reshape(J, 2, st, st)
        else:
            tpl, in_t = sample_patches(img_f, H_f_inv, c_f, offs)
            tpl = tpl.reshape(J, -1, st, st)
            ident = tpl[:, :1]
        K = tpl.shape[1]
        if first_template is None:
            first_template = ident.reshape(J, st, st)
        maps.append(ncc_maps(win, tpl))
        inside_all.append(in_t & in_w)
        valid_all.append(ok_f & ok_m)
        pass_of_k += [p] * K
        k_local += list(range(K))
        templates.append(tpl)
        H_m_invs.append(H_m_inv)
        c_ms.append(c_m)
    allmaps = torch.cat(maps, dim=1)
    lam_min, lam_max, dir_max = structure_tensor(first_template)
    mask = (
        ellipse_masks(lam_min, lam_max, dir_max, cfg.search_radius) if cfg.ellipse_mask else None
    )
    pk = find_peaks(allmaps, mask)
    J = allmaps.shape[0]
    pass_idx = torch.as_tensor(pass_of_k, device=allmaps.device)[pk["k"]]
    offset = torch.stack([pk["dx"], pk["dy"]], -1).to(torch.float64)
    k_in_pass = torch.as_tensor(k_local, device=allmaps.device)[pk["k"]]
    new = torch.empty((J, 2), dtype=torch.float64, device=allmaps.device)
    for p in range(len(pairs)):
        sel = pass_idx == p
        if sel.any():
            Hi = H_m_invs[p][sel]
            off = offset[sel]
            if cfg.subpixel_iterations:
                tpl = templates[p][sel, k_in_pass[sel]]
                off = _iterate_subpixel(img_m, Hi, c_ms[p][sel], off, tpl, cfg)
            tgt = c_ms[p][sel] + off
            num = (Hi[:, :2, :2] @ tgt[:, :, None])[..., 0] + Hi[:, :2, 2]
            den = (Hi[:, 2:, :2] @ tgt[:, :, None])[..., 0] + Hi[:, 2:, 2]
            new[sel] = num / den.clamp_min(1e-12)
    tstd = first_template.reshape(J, -1).to(torch.float64).std(dim=1)
    ratio = torch.where(lam_max > 0, lam_min / lam_max.clamp_min(1e-20), torch.zeros_like(lam_max))
    valid = torch.stack(valid_all).all(dim=0)
    return {
        "peak": pk["peak"].to(torch.float64),
        "centre": pk["centre"].to(torch.float64),
        "border": pk["border"],
        "zero": (pk["ix"] == 0) & (pk["iy"] == 0),
        "new": new,
        "inside": torch.stack(inside_all).all(dim=0),
        "valid": valid,
        "flat": tstd < cfg.min_template_std,
        "edge": ratio < cfg.min_cornerness,
    }


def _iterate_subpixel(img_m, H_m_inv, c_m, offset, tpl, cfg):
    """Re-centre the search window on the sub-pixel estimate and fit the parabolas again on
    the 3x3 NCC neighbourhood, ``cfg.subpixel_iterations`` times. This removes most of the
    bias of a single parabola fit on an integer grid ("pixel locking").

    Shapes: H_m_inv (n, 3, 3), c_m (n, 2), offset (n, 2) float64, tpl (n, St, St) float32.
    Returns the updated offset (n, 2) float64.
    """
    ring = offset_grid(cfg.template_radius + 1, offset.device)[None]
    side = 2 * cfg.template_radius + 3
    active = torch.ones(offset.shape[0], dtype=torch.bool, device=offset.device)
    for _ in range(cfg.subpixel_iterations):
        win, _ = sample_patches(img_m, H_m_inv, c_m + offset, ring)
        m3 = ncc_maps(win.reshape(-1, side, side), tpl[:, None])[:, 0].to(torch.float64)
        c0 = m3[:, 1, 1]

        def vertex(cm, cp):
            den = cm - 2.0 * c0 + cp
            ok = den < -MIN_CURVATURE
            d = 0.5 * (cm - cp) / torch.where(ok, den, torch.ones_like(den))
            return torch.where(ok, d.clamp(-0.5, 0.5), torch.zeros_like(d))

        step = torch.stack([vertex(m3[:, 1, 0], m3[:, 1, 2]), vertex(m3[:, 0, 1], m3[:, 2, 1])], -1)
        # per-match convergence, so that a match's result does not depend on its batch
        offset = offset + torch.where(active[:, None], step, torch.zeros_like(step))
        active = active & (step.abs().amax(dim=1) >= 1e-3)
        if not active.any():
            break
    return offset


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
            float (intensities nominally in [0, 1]).
        pts1, pts2: (N, 2) pixel coordinates (x, y), integer = pixel centre.
        patch_homographies: (N, 2, 3, 3) one pair (A, B) per match mapping image 1 and image 2
            into a common frame, ``A x1 ~ B x2`` (e.g. (I, H_2from1^-1) for MOP, the two
            middle homographies for MiHo).
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

    Raises:
        ValueError: on malformed inputs (shapes, dtypes, device).
    """
    t0 = time.perf_counter()
    cfg = config if config is not None else NCCConfig()
    side = MoveSide.parse(cfg.move if move is None else move, "move")
    p1 = _as_array("pts1", pts1, (2,), None)
    n = p1.shape[0]
    p2 = _as_array("pts2", pts2, (2,), n)
    homs = _as_array("patch_homographies", patch_homographies, (2, 3, 3), n)
    if (affine1 is None) != (affine2 is None):
        raise ValueError("affine1 and affine2 must be given together")
    if affine1 is not None:
        affine1 = _as_array("affine1", affine1, (2, 2), n)
        affine2 = _as_array("affine2", affine2, (2, 2), n)
    homs = _normalise_signs(homs, p1, p2)
    device = _pick_device(cfg, image1, image2, pts1, patch_homographies)
    img = (to_gray_tensor(image1, device), to_gray_tensor(image2, device))

    out1, out2 = p1.copy(), p2.copy()
    before = np.full(n, np.nan)
    after = np.full(n, np.nan)
    moved = np.zeros(n, np.int8)
    disp = np.zeros(n)
    rejected = np.zeros(n, bool)
    counts = dict.fromkeys(
        ["moved", "rejected_border", "rejected_gain", "gated_flat", "gated_edge", "outside",
         "invalid_homography"], 0)

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

    chunks = range(0, n, cfg.batch_size)
    if progress:
        from tqdm import tqdm

        chunks = tqdm(chunks, desc="NCC", unit="chunk")
    with torch.no_grad():
        for start in chunks:
            sl = slice(start, min(start + cfg.batch_size, n))
            x = (torch.as_tensor(p1[sl], device=device), torch.as_tensor(p2[sl], device=device))
            H_ext = torch.as_tensor(homs[sl], device=device)
            pairs = [(H_ext, tpl_off, tpl_off_coarse)]
            if use_base:
                pairs.append((torch.as_tensor(base[sl], device=device), grid_t[None], None))
            res = [
                (f, m, _run_direction(img[f], img[m], x[f], x[m], pairs, f, m, tpl_off, win_off, cfg))
                for f, m in directions
            ]
            _decide(res, sl, cfg, (out1, out2), before, after, moved, disp, rejected, counts)

    counts.update(
        n=n,
        seconds=time.perf_counter() - t0,
        device=str(device),
        shapes=int(shapes.shape[0]) + int(use_base),
        directions=len(directions),
    )
    logger.debug("refine_pair: %s", counts)
    return RefineResult(
        pts1=out1, pts2=out2, ncc_before=before, ncc_after=after, moved_side=moved,
        displacement=disp, rejected=rejected, stats=counts,
    )


def _decide(res, sl, cfg, outs, before, after, moved, disp, rejected, counts) -> None:
    """Choose the direction per match and apply or reject its move (writes into the outputs)."""
    cand = []
    for f, m, r in res:
        r = {k: v.cpu().numpy() for k, v in r.items()}
        usable = r["valid"] & r["inside"] & ~r["flat"]
        if cfg.cornerness_gate:
            usable &= ~r["edge"]
        cand.append((f, m, r, usable))
    score = np.stack([np.where(u, r["peak"], -np.inf) for _, _, r, u in cand])
    best = score.argmax(axis=0)
    idx = np.arange(sl.start, sl.stop)
    for d, (f, m, r, usable) in enumerate(cand):
        rows = best == d
        if d == 0:  # count why nothing could be used, once per match
            none = ~np.stack([u for *_, u in cand]).any(axis=0)
            counts["invalid_homography"] += int((none & ~r["valid"]).sum())
            counts["outside"] += int((none & r["valid"] & ~r["inside"]).sum())
            counts["gated_flat"] += int((none & r["valid"] & r["inside"] & r["flat"]).sum())
            counts["gated_edge"] += int(
                (none & r["valid"] & r["inside"] & ~r["flat"] & r["edge"]).sum()
            )
        rows &= usable
        gi = idx[rows]
        before[gi] = r["centre"][rows]
        after[gi] = r["centre"][rows]
        on_border = r["border"][rows] & cfg.reject_border
        small_gain = ~r["zero"][rows] & (r["peak"][rows] - r["centre"][rows] < cfg.min_gain)
        reject = on_border | small_gain
        counts["rejected_border"] += int(on_border.sum())
        counts["rejected_gain"] += int((small_gain & ~on_border).sum())
        rejected[gi[reject]] = True
        ok = gi[~reject]
        new = r["new"][rows][~reject]
        old = outs[m][ok]
        outs[m][ok] = new
        disp[ok] = np.linalg.norm(new - old, axis=1)
        moved[ok] = m + 1
        after[ok] = r["peak"][rows][~reject]
        counts["moved"] += int(ok.size)
