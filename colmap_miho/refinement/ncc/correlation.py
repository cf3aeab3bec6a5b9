"""Batched normalised cross-correlation maps, structure tensors and peak finding (App. E).

With a zero-mean template the NCC numerator is a plain cross-correlation (one grouped ``conv2d``)
and the window norms come from box sums, so no patch is normalised one by one. NCC is in [-1, 1]
(the paper's S divided by the pixel count)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: a parabola whose curvature (NCC units per px^2) is flatter than this is not fitted: on a
#: flat ridge (along an edge) its vertex is noise.
MIN_CURVATURE = 1e-4
#: a second peak of an NCC map counts as separated from the best one when it lies at least
#: this many offsets from it in x or y (the best peak's own neighbours are its shoulders).
SEPARATED_PX = 2
#: template / window norms below this (intensity units, [0, 1] scale) count as flat.
_EPS_NORM = 1e-6
#: the grouped convolution of :func:`ncc_maps` runs on a multiple of this many groups (the
#: SIMD width of oneDNN's depthwise kernels on AVX2; AVX-512 blocks by 16, a multiple).
_GROUP_PAD = 8
#: On the CPU :func:`ncc_maps` runs on blocks of jobs (a multiple of _GROUP_PAD) of about
#: this many window pixels (256 windows of 33 x 33): the intermediates of a block stay in cache
_BLOCK_PIXELS = 256 * 33 * 33


def normalize_templates(templates: torch.Tensor) -> torch.Tensor:
    """Zero-mean, unit-norm templates ``(J, K, St, St)`` float32; flat ones become zero."""
    # float64 reductions: float32 ones may round differently with the batch size, and a
    # match's result should not depend on which other matches share its batch
    t = templates - _mean64(templates)
    t_norm = t.to(torch.float64).square().sum(dim=(-2, -1), keepdim=True).sqrt().to(t.dtype)
    t = t / t_norm.clamp_min(_EPS_NORM)
    return torch.where(t_norm > _EPS_NORM, t, torch.zeros_like(t))


def ncc_maps(
    windows: torch.Tensor, templates: torch.Tensor, stride: int = 1, normalized: bool = False
) -> torch.Tensor:
    """NCC maps ``(J, K, So, So)`` of every template against its own window, So = (Sw - St) //
    stride + 1.

    ``windows`` ``(J, Sw, Sw)``, ``templates`` ``(J, K, St, St)``; entry ``[j, k, y, x]`` is for the
    patch with top-left corner (stride x, stride y). Flat windows or templates give 0."""
    J, Sw = windows.shape[0], windows.shape[-1]
    block = max(_GROUP_PAD, _BLOCK_PIXELS // (Sw * Sw) // _GROUP_PAD * _GROUP_PAD)
    if J <= block or windows.device.type != "cpu":  # a GPU wants one big call
        return _ncc_block(windows, templates, stride, normalized)
    # blocks of jobs whose intermediates stay in cache (a job's maps do not depend on the
    # other jobs of its call, so the blocks give the same bits as one call)
    out = [_ncc_block(windows[i:i + block], templates[i:i + block], stride, normalized)
           for i in range(0, J, block)]
    return torch.cat(out)


def _ncc_block(
    windows: torch.Tensor, templates: torch.Tensor, stride: int, normalized: bool
) -> torch.Tensor:
    J, K, St, _ = templates.shape
    Sw = windows.shape[-1]
    n = St * St
    t = templates if normalized else normalize_templates(templates)
    # one grouped convolution per shape: oneDNN is much slower on groups with more than
    # one output channel. The group count is padded to a multiple
    # of _GROUP_PAD so that a lone match goes through the same depthwise kernel as a batch
    # (one group is a plain convolution, which sums in another order); the mean-free
    # windows and the kernels are written straight into the padded buffers
    pad = (-J) % _GROUP_PAD
    wp = windows.new_empty((J + pad, Sw, Sw))
    tk = t.new_empty((K, J + pad, 1, St, St))  # each shape's kernels contiguous
    if pad:
        wp[J:] = 0.0
        tk[:, J:] = 0.0
    w = torch.sub(windows, _mean64(windows), out=wp[:J])  # limits float32 cancellation
    tk[:, :J, 0] = t.transpose(0, 1)
    win4 = wp[None]
    if K == 1:
        num = F.conv2d(win4, tk[0], groups=J + pad, stride=stride)[0, :J, None]
    else:
        num = torch.stack(
            [F.conv2d(win4, tk[k], groups=J + pad, stride=stride)[0, :J] for k in range(K)],
            dim=1)
    s1 = box_sum(w, St)
    s2 = box_sum(w.square(), St)
    # in place, the same operations as the plain form (tested against it):
    #   w_norm = (s2 - s1.square() / n).clamp_min(0.0).sqrt()
    #   inv = torch.where(w_norm > eps, 1.0 / w_norm.clamp_min(eps), 0.0)
    #   (num * inv).clamp_(-1.0, 1.0)
    # where 1.0 / x is torch's reciprocal(x) * 1.0, the product exact
    w_norm = s2.sub_(s1.square_().div_(n)).clamp_min_(0.0).sqrt_()[:, None, ::stride, ::stride]
    inv = w_norm.clamp_min(_EPS_NORM).reciprocal_()
    inv.masked_fill_((w_norm > _EPS_NORM).logical_not_(), 0.0)
    return num.mul_(inv).clamp_(-1.0, 1.0)


def _mean64(x: torch.Tensor) -> torch.Tensor:
    """Mean over the last two axes summed in float64, returned in x's dtype."""
    return x.mean(dim=(-2, -1), keepdim=True, dtype=torch.float64).to(x.dtype)


def box_sum(x: torch.Tensor, size: int) -> torch.Tensor:
    """Sums over all ``size`` x ``size`` windows of x ``(J, S, S)`` by separable running sums
    (sequential, so a value never depends on the batch)."""
    J, S = x.shape[0], x.shape[-1]
    o = S - size + 1
    # window [j, j + size) = c[j + size - 1] - c[j - 1], the first one c[size - 1] - 0
    c = x.cumsum(-1)
    rows = x.new_empty((J, S, o))
    rows[..., 0] = c[..., size - 1]
    torch.sub(c[..., size:], c[..., : S - size], out=rows[..., 1:])
    c = rows.cumsum(-2)
    out = x.new_empty((J, o, o))
    out[:, 0] = c[:, size - 1]
    torch.sub(c[:, size:], c[:, : S - size], out=out[:, 1:])
    return out


def structure_tensor(patches: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(lam_min, lam_max (J,), dir_max (J, 2))``: eigenvalues of each patch's gradient structure
    tensor and the unit direction of the dominant gradient."""
    patches = patches.to(torch.float64)  # batch-independent sums
    gx = 0.5 * (patches[:, 1:-1, 2:] - patches[:, 1:-1, :-2])
    gy = 0.5 * (patches[:, 2:, 1:-1] - patches[:, :-2, 1:-1])
    a = gx.square().sum(dim=(-2, -1))
    b = (gx * gy).sum(dim=(-2, -1))
    c = gy.square().sum(dim=(-2, -1))
    half_tr = 0.5 * (a + c)
    disc = (0.25 * (a - c).square() + b.square()).sqrt()
    lam_max = half_tr + disc
    lam_min = (half_tr - disc).clamp_min(0.0)
    # eigenvector of lam_max: (b, lam_max - a) or (lam_max - c, b), whichever is larger
    v1 = torch.stack([b, lam_max - a], -1)
    v2 = torch.stack([lam_max - c, b], -1)
    v = torch.where((v1.norm(dim=-1) >= v2.norm(dim=-1))[:, None], v1, v2)
    nv = v.norm(dim=-1, keepdim=True)
    default = torch.tensor([1.0, 0.0], dtype=v.dtype, device=v.device).expand_as(v)
    dir_max = torch.where(nv > 1e-12, v / nv.clamp_min(1e-12), default)
    return lam_min, lam_max, dir_max


def ellipse_masks(
    lam_min: torch.Tensor,
    lam_max: torch.Tensor,
    dir_max: torch.Tensor,
    radius: int,
    min_axis: float = 0.5,
) -> torch.Tensor:
    """NCC* masks ``(J, 2r+1, 2r+1)`` ``[y, x]``: an ellipse of semi-axis ``radius`` across the edge
    and ``max(min_axis, radius sqrt(lam_min / lam_max))`` along it."""
    r = torch.arange(-radius, radius + 1, device=lam_min.device, dtype=torch.float32)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    ratio = torch.where(lam_max > 0, lam_min / lam_max.clamp_min(1e-20), torch.ones_like(lam_max))
    minor = (radius * ratio.sqrt()).clamp_min(min_axis)
    d = dir_max.to(torch.float32)
    along_grad = xx[None] * d[:, 0, None, None] + yy[None] * d[:, 1, None, None]
    along_edge = -xx[None] * d[:, 1, None, None] + yy[None] * d[:, 0, None, None]
    q = (along_grad / radius).square() + (along_edge / minor[:, None, None]).square()
    return q <= 1.0 + 1e-6


def parabola_vertex(
    c0: torch.Tensor, cm: torch.Tensor, cp: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """Vertex of the parabola through (-1, cm), (0, c0), (1, cp), clamped to [-0.5, 0.5]; 0 where
    invalid or too flat (``MIN_CURVATURE``)."""
    den = cm - 2.0 * c0 + cp
    ok = den < -MIN_CURVATURE
    if valid is not None:
        ok = valid & ok
    d = 0.5 * (cm - cp) / torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, d.clamp(-0.5, 0.5), torch.zeros_like(d))


def find_peaks(maps: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Best shape and offset per job with parabolic sub-pixel refinement: a dict of ``(J,)``
    tensors.

    ``k``, ``peak``, integer ``ix``/``iy`` and sub-pixel ``dx``/``dy`` offsets from the centre,
    ``border`` (on the border or held back by ``mask``), ``centre`` (NCC at zero offset) and
    ``second`` (best local maximum at least :data:`SEPARATED_PX` away, at least -1)."""
    J, K, So, _ = maps.shape
    s = So // 2
    m = maps if mask is None else maps.masked_fill(~mask[:, None], -2.0)
    flat = m.reshape(J, -1)
    peak, arg = flat.max(dim=1)
    k = arg // (So * So)
    rem = arg % (So * So)
    iy, ix = rem // So, rem % So
    best = maps[torch.arange(J, device=maps.device), k]  # (J, So, So)
    jj = torch.arange(J, device=maps.device)

    vx = (ix > 0) & (ix < So - 1)
    vy = (iy > 0) & (iy < So - 1)
    c0 = best[jj, iy, ix]
    sub_x = parabola_vertex(c0, best[jj, iy, (ix - 1).clamp_min(0)], best[jj, iy, (ix + 1).clamp_max(So - 1)], vx)
    sub_y = parabola_vertex(c0, best[jj, (iy - 1).clamp_min(0), ix], best[jj, (iy + 1).clamp_max(So - 1), ix], vy)
    border = ~(vx & vy)
    if mask is not None:
        # a peak held back by the mask is not a local maximum of the unmasked map
        local_max = F.max_pool2d(best[:, None], 3, stride=1, padding=1)[:, 0]
        border = border | (local_max[jj, iy, ix] > c0 + 1e-6)
    centre = maps[:, :, s, s].max(dim=1).values
    m_best = m[jj, k]  # (J, So, So), masked
    local = m_best >= F.max_pool2d(m_best[:, None], 3, stride=1, padding=1)[:, 0]
    o = torch.arange(So, device=maps.device)
    apart = (((o[None, :, None] - iy[:, None, None]).abs() >= SEPARATED_PX)
             | ((o[None, None, :] - ix[:, None, None]).abs() >= SEPARATED_PX))
    second = torch.where(local & apart, m_best, torch.full_like(m_best, -1.0)).amax(dim=(1, 2)).clamp_min(-1.0)
    return {
        "k": k,
        "peak": peak,
        "ix": ix - s,
        "iy": iy - s,
        "dx": (ix - s).to(maps.dtype) + sub_x,
        "dy": (iy - s).to(maps.dtype) + sub_y,
        "border": border,
        "centre": centre,
        "second": second,
    }
