"""One direction of the NCC search: templates from the fixed side searched in the moving side, per
homography pair ("pass") in its common frame (window sampled once). The reference of
:func:`.kernel.evaluate`, and the path on CUDA and for perturbed shapes."""

from __future__ import annotations

import torch

from ..config import NCCConfig
from ..warping import (
    ImageStack,
    invert_homographies,
    job_images,
    offset_grid,
    patch_inside,
    sample_patches,
    sample_values,
    to_frame,
)
from . import kernel
from .correlation import ellipse_masks, find_peaks, ncc_maps, structure_tensor

#: one pass of the search: (J, 2, 3, 3) float64 homography pairs, template offsets (K, P, 2),
#: the same shapes sampled every 2 px (K, Pc, 2) or None.
Pass = tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]


def _repeat(image: torch.Tensor | ImageStack, n: int) -> torch.Tensor | ImageStack:
    if isinstance(image, ImageStack):
        return ImageStack(image.images, image.slot_sizes, image.index.repeat(n))
    return image


def _templates(
    img_f: torch.Tensor | ImageStack,
    H_f_inv: torch.Tensor,
    c_f: torch.Tensor,
    win: torch.Tensor,
    offs: torch.Tensor,
    offs_coarse: torch.Tensor | None,
    cfg: NCCConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Templates ``(J, K', St, St)`` to search at full resolution (K' = 2 after a coarse shape
    choice, else every shape), and whether they are inside."""
    J = c_f.shape[0]
    st = 2 * cfg.template_radius + 1
    if offs.shape[0] == 1 or not cfg.coarse_shapes:
        tpl, inside = sample_patches(img_f, H_f_inv, c_f, offs)
        return tpl.reshape(J, -1, st, st), inside
    # shapes compared with templates sampled every 2 px against the window's even pixels:
    # about 4x fewer samples and 10x fewer multiply-adds than a full-resolution search
    assert offs_coarse is not None  # given with every multi-shape pass
    tpl_c, inside = sample_patches(img_f, H_f_inv, c_f, offs_coarse)
    sc = int(round(offs_coarse.shape[1] ** 0.5))
    coarse = ncc_maps(win[:, ::2, ::2], tpl_c.reshape(J, -1, sc, sc))
    best = coarse.reshape(J, offs.shape[0], -1).amax(dim=-1).argmax(dim=1)
    # the unperturbed shape always competes at full resolution too: the coarse choice is
    # blurred by aliasing
    both = torch.stack([torch.zeros_like(best), best], dim=1)  # (J, 2)
    tpl, in_full = sample_patches(img_f, H_f_inv, c_f, offs[both])  # offsets (J, 2, P, 2)
    return tpl.reshape(J, 2, st, st), inside & in_full


def _search_passes(
    img_f: torch.Tensor | ImageStack,
    H_f_inv: torch.Tensor,
    c_f: torch.Tensor,
    win_all: torch.Tensor,
    passes: list[Pass],
    cfg: NCCConfig,
) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor]:
    """Templates and NCC maps of each pass, and whether each template is inside (pass-major)."""
    n_pass = len(passes)
    J = win_all.shape[0] // n_pass
    st = 2 * cfg.template_radius + 1
    plain = all(offs.shape[0] == 1 and torch.equal(offs, passes[0][1]) for _, offs, _ in passes)
    if plain:  # one template shape, the same in every pass (no coarse choice of shapes)
        tpl_all, in_t = sample_patches(_repeat(img_f, n_pass), H_f_inv, c_f, passes[0][1])
        tpl_all = tpl_all.reshape(n_pass * J, 1, st, st)
        map_all = ncc_maps(win_all, tpl_all)
        return list(tpl_all.split(J)), list(map_all.split(J)), in_t
    templates, maps, ins = [], [], []
    for p, (_, offs, offs_coarse) in enumerate(passes):
        sl = slice(p * J, (p + 1) * J)
        tpl, in_p = _templates(img_f, H_f_inv[sl], c_f[sl], win_all[sl], offs, offs_coarse, cfg)
        templates.append(tpl)
        maps.append(ncc_maps(win_all[sl], tpl))
        ins.append(in_p)
    return templates, maps, torch.cat(ins)


def evaluate_direction(
    img_f: torch.Tensor | ImageStack,
    img_m: torch.Tensor | ImageStack,
    x_f: torch.Tensor,
    x_m: torch.Tensor,
    passes: list[Pass],
    f: int,
    m: int,
    win_off: torch.Tensor,
    cfg: NCCConfig,
    compiled: bool | None = None,
) -> dict[str, torch.Tensor]:
    """Best NCC peak over all passes and shapes for J matches in one direction.

    With ``cfg.inner_radius`` only the matches whose peak climbs out of the smaller window are
    searched again over the full radius. ``passes``: :data:`Pass` tuples (homography pairs ``(J, 2,
    3, 3)``, template offsets, coarse offsets or None); ``f``, ``m``: the fixed and moving side's
    index in each pair. Returns a dict of J-row tensors: ``peak``, ``centre``, ``second``,
    ``border``, ``zero``, ``inside``, ``valid``, ``flat``, the peak's common-frame ``offset``, the
    winning pass's ``H_inv``, ``frame_m``, ``template`` and, for LSM, ``H_f_inv`` and ``frame_f``."""
    if compiled is None:
        compiled = x_f.device.type == "cpu" and kernel.serves(passes, cfg.template_radius)
    if compiled:
        r = kernel.evaluate(img_f, img_m, x_f, x_m, passes, f, m, template_radius=cfg.template_radius,
                                search_radius=cfg.search_radius, inner_radius=cfg.inner_radius,
                                ellipse_mask=cfg.ellipse_mask, min_template_std=cfg.min_template_std)
        r.pop("researched")
        return r
    s0 = cfg.inner_radius
    if not 0 < s0 < cfg.search_radius:
        return _evaluate(img_f, img_m, x_f, x_m, passes, (f, m), (win_off, None), cfg.search_radius, cfg)
    near = offset_grid(cfg.template_radius + s0, win_off.device, win_off.dtype)
    r = _evaluate(img_f, img_m, x_f, x_m, passes, (f, m), (near, win_off), s0, cfg)
    # the inside test is the full window's already: only usable matches are searched again
    far = torch.nonzero(r.pop("near_border") & r["valid"] & r["inside"] & ~r["flat"])[:, 0]
    if far.numel():
        full = _evaluate(job_images(img_f, far), job_images(img_m, far), x_f[far], x_m[far],
                         [(H[far], offs, coarse) for H, offs, coarse in passes], (f, m),
                         (win_off, None), cfg.search_radius, cfg)
        for key, value in full.items():
            r[key][far] = value
    return r


def _evaluate(
    img_f: torch.Tensor | ImageStack,
    img_m: torch.Tensor | ImageStack,
    x_f: torch.Tensor,
    x_m: torch.Tensor,
    passes: list[Pass],
    sides: tuple[int, int],
    windows: tuple[torch.Tensor, torch.Tensor | None],
    radius: int,
    cfg: NCCConfig,
) -> dict[str, torch.Tensor]:
    """:func:`evaluate_direction` over offsets up to ``radius``; ``windows``: the window offsets and
    those whose square the inside test checks (None: the window's own)."""
    f, m = sides
    win_off, outer = windows
    st = 2 * cfg.template_radius + 1
    sw = 2 * (cfg.template_radius + radius) + 1
    J, n_pass = x_f.shape[0], len(passes)
    # the passes as one batch of n_pass * J jobs (pass-major): every job's samples and NCC
    # are its own whatever the batch, and one call per step costs less than one per pass
    H_f = torch.cat([H[:, f] for H, _, _ in passes])
    H_m = torch.cat([H[:, m] for H, _, _ in passes])
    H_f_inv, ok_f = invert_homographies(H_f)
    H_m_inv, ok_m = invert_homographies(H_m)
    c_f = to_frame(H_f, x_f.repeat(n_pass, 1))
    c_m = to_frame(H_m, x_m.repeat(n_pass, 1))
    if outer is None:
        win_all, in_w = sample_patches(_repeat(img_m, n_pass), H_m_inv, c_m, win_off[None])
    else:
        win_all, in_w = sample_values(_repeat(img_m, n_pass), H_m_inv, c_m, win_off[None])
        in_w = in_w & patch_inside(_repeat(img_m, n_pass), H_m_inv, c_m, outer[None])
    win_all = win_all.reshape(n_pass * J, sw, sw)
    templates, maps, in_t = _search_passes(img_f, H_f_inv, c_f, win_all, passes, cfg)
    pass_of_k = [p for p, tpl in enumerate(templates) for _ in range(tpl.shape[1])]
    inside = list((in_t & in_w).split(J))
    valid = list((ok_f & ok_m).split(J))
    H_invs = list(H_m_inv.split(J))
    frames = list(c_m.split(J))
    first_template = templates[0][:, 0]  # the unperturbed template of the first pass
    allmaps = torch.cat(maps, dim=1)
    lam_min, lam_max, dir_max = structure_tensor(first_template)
    mask = None
    if cfg.ellipse_mask:  # the full search's ellipse, cut to the offsets searched here
        mask = ellipse_masks(lam_min, lam_max, dir_max, cfg.search_radius)
        cut = cfg.search_radius - radius
        mask = mask[:, cut:mask.shape[1] - cut, cut:mask.shape[2] - cut]
    pk = find_peaks(allmaps, mask)
    near_border = None
    if outer is not None:  # the peak of each pass and shape on its own: any on the border?
        K = allmaps.shape[1]
        each = find_peaks(allmaps.reshape(-1, 1, *allmaps.shape[2:]),
                          None if mask is None else mask.repeat_interleave(K, dim=0))
        near_border = each["border"].reshape(-1, K).any(dim=1)
    J = allmaps.shape[0]
    rows = torch.arange(J, device=allmaps.device)
    pass_idx = torch.as_tensor(pass_of_k, device=allmaps.device)[pk["k"]]
    all_tpl = torch.cat(templates, dim=1)  # (J, sum K', St, St)
    H_inv = torch.stack(H_invs, dim=1)[rows, pass_idx]
    frame_m = torch.stack(frames, dim=1)[rows, pass_idx]
    H_f_win = torch.stack(list(H_f_inv.split(J)), dim=1)[rows, pass_idx]
    frame_f = torch.stack(list(c_f.split(J)), dim=1)[rows, pass_idx]
    tstd = first_template.reshape(J, -1).to(torch.float64).std(dim=1)
    out = {
        "peak": pk["peak"].to(torch.float64),
        "centre": pk["centre"].to(torch.float64),
        "second": pk["second"].to(torch.float64),
        "border": pk["border"],
        "zero": (pk["ix"] == 0) & (pk["iy"] == 0),
        "inside": torch.stack(inside).all(dim=0),
        "valid": torch.stack(valid).all(dim=0),
        "flat": tstd < cfg.min_template_std,
        "offset": torch.stack([pk["dx"], pk["dy"]], -1).to(torch.float64),
        "H_inv": H_inv,
        "frame_m": frame_m,
        "H_f_inv": H_f_win,
        "frame_f": frame_f,
        "template": all_tpl[rows, pk["k"]].reshape(J, st, st),
    }
    if near_border is not None:
        out["near_border"] = near_border
    return out
