"""Batched homography patch sampling with torch (bilinear, pixel centres at integers).

All coordinates are (x, y) pixels with integer = pixel centre (OpenCV / kornia convention).
A patch homography ``H`` maps image pixels into a common (rectified) frame: ``c ~ H x``.
Sampling a patch around a common-frame centre ``c`` reads the image at ``H^-1 (c + w)`` for the
offsets ``w`` of a square grid, with ``torch.nn.functional.grid_sample`` (bilinear,
``align_corners=True``, which puts pixel centres at integers).

On the CPU a job's samples are bitwise independent of the other jobs of the call (how many,
in which order, which images are stacked with its own): the track walk groups matches
differently with the chunking and must give the same result. So no GEMM and no reduction
runs across jobs here: small matrix products are written out elementwise, and each job is
sampled in the grid coordinates of its own image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InvalidInput

#: |det H| below this (relative to the scale of H) marks a homography as singular.
_SINGULAR_DET = 1e-12
#: homogeneous w below this marks a point mapped to (or behind) the line at infinity.
_MIN_W = 1e-8
#: coordinates used for samples that cannot be mapped: far outside every image (reads zero).
_FAR = -1.0e6
#: :func:`sample_values` samples each run of consecutive jobs of one image (and map kind)
#: into its rows of the output when there are at most this many runs, else it sorts the jobs
#: by image once (fewer, larger ``grid_sample`` calls).
_MAX_RUNS = 64
#: per-job image indices: (J,) int numpy array, tensor or sequence.
IndexLike = np.ndarray | torch.Tensor | Sequence[int]


@overload
def to_gray_tensor(image: ImageStack, device: torch.device) -> ImageStack: ...
@overload
def to_gray_tensor(image: np.ndarray | torch.Tensor, device: torch.device) -> torch.Tensor: ...
def to_gray_tensor(
    image: np.ndarray | torch.Tensor | ImageStack, device: torch.device
) -> torch.Tensor | ImageStack:
    """Image as a float32 tensor (H, W) on ``device`` (an :class:`ImageStack` is returned
    as is).

    Args:
        image: numpy array or tensor (H, W), uint8 (divided by 255) or float (used as is,
            intensities nominally in [0, 1]).
    """
    if isinstance(image, ImageStack):
        return image
    if isinstance(image, torch.Tensor):
        t = image.detach()
    elif isinstance(image, np.ndarray):
        t = torch.from_numpy(np.ascontiguousarray(image))
    else:
        raise InvalidInput(f"image must be a grayscale (H, W) numpy array or torch tensor, got {type(image).__name__} "
                           "(read a file first, e.g. cv2.imread(path, cv2.IMREAD_GRAYSCALE))")
    if t.ndim != 2:
        raise InvalidInput(f"image must be a grayscale (H, W) array, got shape {tuple(t.shape)}")
    if min(t.shape) == 0:
        raise InvalidInput(f"image must hold pixels, got shape {tuple(t.shape)}")
    if t.dtype == torch.uint8:
        t = t.to(torch.float32) / 255.0
    elif t.is_floating_point():
        t = t.to(torch.float32)
    else:
        raise InvalidInput(f"image must be uint8 or float, got dtype {t.dtype}")
    return t.to(device)


@dataclass(frozen=True)
class ImageStack:
    """Several images for one batch of jobs: job j reads image ``index[j]`` of ``images``.

    Lets one batched call serve matches of many image pairs (the track walk on a GPU, where
    a call costs little more for many matches than for few). The images keep their own
    sizes (no padded copy); a job reads its own image only (samples outside it read zero,
    as for that image alone), so its values do not depend on the other images.

    Attributes:
        images: D (H_d, W_d) float32 tensors, on one device.
        slot_sizes: (D, 2) float64 (width, height) of each image.
        index: (J,) int64 image of each job.
    """

    images: tuple
    slot_sizes: torch.Tensor
    index: torch.Tensor

    @classmethod
    def build(cls, images: list[torch.Tensor], index: IndexLike, device: torch.device) -> ImageStack:
        """Hold (H, W) float32 tensors (moved to ``device``, not copied when already
        there); ``index`` (J,) picks each job's image."""
        if not images:
            raise ValueError("an ImageStack needs at least one image")
        ims = tuple(im.to(device) for im in images)
        wh = torch.tensor([[im.shape[1], im.shape[0]] for im in ims], dtype=torch.float64,
                          device=device)
        return cls(ims, wh, torch.as_tensor(index, dtype=torch.int64, device=device))

    def with_index(self, index: IndexLike) -> ImageStack:
        """The same images, read by other jobs."""
        return ImageStack(self.images, self.slot_sizes,
                          torch.as_tensor(index, dtype=torch.int64, device=self.device))

    def rows(self, sel: slice | torch.Tensor) -> ImageStack:
        """The same images for a subset (slice or index tensor) of the jobs."""
        return ImageStack(self.images, self.slot_sizes, self.index[sel])

    @property
    def sizes(self) -> torch.Tensor:
        """(J, 2) float64 (width, height) of each job's image."""
        return self.slot_sizes[self.index]

    @property
    def device(self) -> torch.device:
        return self.index.device


def job_images(image: torch.Tensor | ImageStack, rows: slice | torch.Tensor
               ) -> torch.Tensor | ImageStack:
    """The images of the jobs ``rows`` (slice or index tensor): the stack's rows, or a plain
    image, which serves every job."""
    return image.rows(rows) if isinstance(image, ImageStack) else image


def image_arrays(image: torch.Tensor | ImageStack, n: int) -> tuple[list[np.ndarray], np.ndarray]:
    """For the compiled CPU kernels: the images as float32 numpy views (no copy of a
    contiguous CPU tensor) and each of the n jobs' index into them (int64; all 0 for a plain
    image)."""
    if isinstance(image, ImageStack):
        return ([im.contiguous().numpy() for im in image.images],
                image.index.cpu().numpy().astype(np.int64))
    return [image.contiguous().numpy()], np.zeros(n, np.int64)


def offset_grid(radius: int, device: torch.device, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Integer offsets of a (2r+1) x (2r+1) square, (P, 2) as (x, y), row-major (y outer),
    so that a tensor (..., P) reshapes to (..., 2r+1, 2r+1) indexed [y, x]."""
    r = torch.arange(-radius, radius + 1, device=device, dtype=dtype)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def invert_homographies(H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched 3x3 inverse by the adjugate.

    Args:
        H: (..., 3, 3) float64.
    Returns:
        (H_inv (..., 3, 3), valid (...) bool); singular or non-finite matrices get the
        identity as inverse and ``valid=False``.
    """
    a, b, c = H[..., 0, 0], H[..., 0, 1], H[..., 0, 2]
    d, e, f = H[..., 1, 0], H[..., 1, 1], H[..., 1, 2]
    g, h, i = H[..., 2, 0], H[..., 2, 1], H[..., 2, 2]
    adj = torch.stack(
        [
            torch.stack([e * i - f * h, c * h - b * i, b * f - c * e], -1),
            torch.stack([f * g - d * i, a * i - c * g, c * d - a * f], -1),
            torch.stack([d * h - e * g, b * g - a * h, a * e - b * d], -1),
        ],
        -2,
    )
    det = a * adj[..., 0, 0] + b * adj[..., 1, 0] + c * adj[..., 2, 0]
    scale = H.abs().amax(dim=(-2, -1)).clamp_min(1e-300) ** 3
    valid = torch.isfinite(det) & (det.abs() > _SINGULAR_DET * scale)
    safe = torch.where(valid, det, torch.ones_like(det))
    inv = adj / safe[..., None, None]
    eye = torch.eye(3, dtype=H.dtype, device=H.device).expand_as(H)
    inv = torch.where(valid[..., None, None], inv, eye)
    return inv, valid


def project(H: torch.Tensor, x: torch.Tensor, y: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Homogeneous image ``H [x; y; 1]`` of points, by elementwise products (no matmul, whose
    rounding may depend on the batch size: a point's result must not depend on the others).

    Args:
        H: (J, 3, 3).
        x, y: (J,) or (J, Q) coordinates, row j mapped by ``H[j]``.
    Returns:
        (X, Y, W) shaped like ``x``, each ``(H[r, 0] x + H[r, 1] y) + H[r, 2]``.
    """
    shape = (H.shape[0], 3) + (1,) * (x.ndim - 1)  # (J, 3, 1, ...) against (J, 1, ...)
    h0, h1, h2 = (H[..., c].reshape(shape) for c in range(3))
    xyw = h0 * x[:, None] + h1 * y[:, None] + h2
    return xyw[:, 0], xyw[:, 1], xyw[:, 2]


def apply_homographies(H: torch.Tensor, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Map points by per-batch homographies.

    Args:
        H: (J, 3, 3) float64.
        pts: (J, P, 2) float64 (x, y).
    Returns:
        (mapped (J, P, 2), ok (J, P) bool); points that land at or behind the line at
        infinity get ``ok=False`` and a far-away coordinate.
    """
    X, Y, W = project(H, pts[..., 0], pts[..., 1])
    ok = W > _MIN_W
    w = torch.where(ok, W, torch.ones_like(W))
    out = torch.stack([X / w, Y / w], dim=-1)
    out = torch.where(ok[..., None], out, torch.full_like(out, _FAR))
    return out, ok


def sample_patches(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    offsets: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample square patches of the rectified image around common-frame centres.

    The centre is mapped in float64; the (small) offsets are mapped relative to it in float32
    (``x = x_c + (B o - x_c (b . o)) / (1 + b . o)``, with ``H^-1 = [B | a]`` normalised so that
    the centre's homogeneous w is 1), which keeps sub-1e-3 pixel accuracy at a fraction of the
    cost of mapping every sample in float64.

    A job's values are bitwise the same whatever the other jobs of the call (their number,
    order, images, the sizes of the images stacked with its own): the sample positions are
    computed by elementwise products and sums (a GEMM rounds differently with the batch
    size), in the grid coordinates of the job's own image, and ``grid_sample`` (one
    sample at a time) reads that image alone.

    Args:
        image: (H, W) float32, or an :class:`ImageStack` with one image per job.
        H_inv: (J, 3, 3) float64, maps the common frame back to image pixels.
        centres: (J, 2) float64 common-frame centres.
        offsets: (K, P, 2) float64 common-frame offsets (K shapes of P = (2r+1)^2 pixels,
            row-major as :func:`offset_grid`) shared by all jobs, or (J, K, P, 2) one set
            per job.
    Returns:
        (values (J, K, P) float32, inside (J,) bool: the patch corners of every shape map
        in front of the camera and inside the image, so the whole patch does).
    """
    values, good = sample_values(image, H_inv, centres, offsets)
    return values, patch_inside(image, H_inv, centres, offsets) & good


def patch_inside(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    offsets: torch.Tensor,
) -> torch.Tensor:
    """The inside test of :func:`sample_patches` alone (no sample read): (J,) bool, the
    corners of every shape's square of offsets map in front of the camera and inside the
    job's image. Arguments as :func:`sample_patches`."""
    J = centres.shape[0]
    K, P = offsets.shape[-3], offsets.shape[-2]
    side = int(round(P**0.5))
    corner_idx = torch.tensor([0, side - 1, P - side, P - 1], device=offsets.device)
    corner_off = offsets[..., corner_idx, :]
    corners = centres[:, None, None, :] + (corner_off if offsets.ndim == 4 else corner_off[None])
    c_img, ok = apply_homographies(H_inv, corners.reshape(J, K * 4, 2))
    size = _job_sizes(image, J)
    return (
        ok
        & (c_img[..., 0] >= 0)
        & (c_img[..., 0] <= size[:, 0:1] - 1)
        & (c_img[..., 1] >= 0)
        & (c_img[..., 1] <= size[:, 1:2] - 1)
    ).all(dim=1)


def _job_sizes(image: torch.Tensor | ImageStack, n: int) -> torch.Tensor:
    """(n, 2) float64 (width, height) of each job's image."""
    if isinstance(image, ImageStack):
        return image.sizes
    return torch.tensor([[image.shape[1], image.shape[0]]], dtype=torch.float64,
                        device=image.device).expand(n, 2)


def sample_values(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    offsets: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The samples of :func:`sample_patches` (the same bits) without its inside test (the
    patch corners), for callers that do not need it.

    Args: as :func:`sample_patches`.
    Returns:
        (values (J, K, P) float32, good (J,) bool: the centre maps in front of the camera).
    """
    J = centres.shape[0]
    per_job = offsets.ndim == 4
    K, P = offsets.shape[-3], offsets.shape[-2]
    M, good = _grid_maps(H_inv, centres, _job_sizes(image, J))
    o = offsets.to(torch.float32).reshape(J if per_job else 1, K * P, 2)
    axes = None if per_job else _square_axes(o)
    # jobs grouped by image and by whether their map is affine (w = 1 exactly: no
    # division): run by run where the jobs come in few runs (no sort, no gather), else
    # sorted by group
    M32 = M.to(torch.float32)
    persp = ((M32[:, 2, :2] != 0).any(dim=1) | (M32[:, 2, 2] != 1)).to(torch.int64)
    key = 2 * image.index + persp if isinstance(image, ImageStack) else persp
    values = torch.empty((J, K * P), dtype=torch.float32, device=centres.device)
    if J == 0:
        return values.reshape(J, K, P), good
    cut = torch.nonzero(key[1:] != key[:-1])[:, 0] + 1
    if cut.numel() <= _MAX_RUNS:
        bounds = [0, *(cut.tolist()), J]
        keys = key[torch.as_tensor(bounds[:-1], device=key.device)].tolist()
        for a, b, g in zip(bounds[:-1], bounds[1:], keys, strict=True):
            img = image.images[g // 2] if isinstance(image, ImageStack) else image
            run = _sample(img, _grid(M32[a:b], o[a:b] if per_job else o, axes, g % 2 == 0))
            if b - a == J:  # one run: no copy
                return run.reshape(J, K, P), good
            values[a:b] = run
        return values.reshape(J, K, P), good
    n_img = len(image.images) if isinstance(image, ImageStack) else 1
    counts = torch.bincount(key, minlength=2 * n_img).tolist()
    order = torch.argsort(key, stable=True)
    M32, o = M32[order], (o[order] if per_job else o)
    start = 0
    for g, count in enumerate(counts):
        if count == 0:
            continue
        sl = slice(start, start + count)
        img = image.images[g // 2] if isinstance(image, ImageStack) else image
        values.index_copy_(0, order[sl],
                           _sample(img, _grid(M32[sl], o[sl] if per_job else o, axes, g % 2 == 0)))
        start += count
    return values.reshape(J, K, P), good


def _grid_maps(H_inv: torch.Tensor, centres: torch.Tensor, size: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per job, the 3x3 map M from common-frame offsets o to ``grid_sample`` coordinates of
    the job's own image (``align_corners=True``): grid = (M [o; 1])_xy / (M [o; 1])_w.

    Args:
        H_inv: (J, 3, 3) float64; centres: (J, 2) float64 common frame; size: (J, 2) float64
            (width, height) of each job's image.
    Returns:
        (M (J, 3, 3) float64, good (J,) bool: the centre maps in front of the camera).
    """
    X, Y, Wc = project(H_inv, centres[:, 0], centres[:, 1])
    good = Wc > _MIN_W
    wc = torch.where(good, Wc, torch.ones_like(Wc))
    xc = torch.stack([X / wc, Y / wc], dim=1)  # (J, 2) float64 image pixels
    scale = 2.0 / (size - 1.0).clamp_min(1.0)  # (J, 2) pixels -> grid units
    Bn = H_inv[:, :, :2] / wc[:, None, None]  # (J, 3, 2): columns of H^-1 acting on offsets
    b = Bn[:, 2]  # (J, 2)
    num_m = (Bn[:, :2] - xc[:, :, None] * b[:, None, :]) * scale[:, :, None]  # (J, 2, 2)
    base = xc * scale - 1.0  # (J, 2) grid coordinates of the centre
    # grid = base + (num_m o) / (1 + b . o) = q_xy / q_w with q = M [o; 1]
    M = torch.zeros((H_inv.shape[0], 3, 3), dtype=torch.float64, device=H_inv.device)
    M[:, :2, :2] = num_m + base[:, :, None] * b[:, None, :]
    M[:, :2, 2] = base
    M[:, 2, :2] = b
    M[:, 2, 2] = 1.0
    return M, good


def _square_axes(o: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(xs, ys)`` (S,) when the shared offsets o (1, S*S, 2) form a row-major square grid
    (``o[y * S + x] = (xs[x], ys[y])``, as :func:`offset_grid`), else None."""
    q = o.shape[1]
    side = int(round(q**0.5))
    if o.shape[0] != 1 or side * side != q:
        return None
    g = o[0].reshape(side, side, 2)
    xs, ys = g[0, :, 0], g[:, 0, 1]
    if not (torch.equal(g[..., 0], xs[None].expand(side, side))
            and torch.equal(g[..., 1], ys[:, None].expand(side, side))):
        return None
    return xs.contiguous(), ys.contiguous()


def _grid(M32: torch.Tensor, o: torch.Tensor, axes: tuple[torch.Tensor, torch.Tensor] | None,
          affine: bool) -> torch.Tensor:
    """``grid_sample`` coordinates (n, Q, 2) float32, grid = (M [o; 1])_xy / (M [o; 1])_w,
    for the n jobs of M32 (n, 3, 3) float32 and the offsets o (1 or n, Q, 2) float32
    (``axes``: those of :func:`_square_axes`, or None), by elementwise float32 operations
    (no GEMM: each job's result is independent of n).

    Every coordinate is ``(m0 ox + m1 oy) + m2`` rounded after each operation, then divided
    by the clamped w. On a square grid of offsets the products are taken once per column
    and per row (the same roundings). ``affine``: every job's map has the last row
    (0, 0, 1), so w = (0 ox + 0 oy) + 1 = 1 exactly and the division, exact, is left out."""
    if axes is not None:
        return _grid_square(M32, axes, affine)
    n, q = M32.shape[0], o.shape[1]
    grid = torch.empty((n, q, 2), dtype=torch.float32, device=M32.device)

    def row(r: int, out: torch.Tensor | None = None) -> torch.Tensor:
        m = M32[:, r, :, None]  # (n, 3, 1)
        v = m[:, 0] * o[..., 0]
        v += m[:, 1] * o[..., 1]
        if out is not None:
            out.copy_(v)
            v = out
        v += m[:, 2]
        return v  # (n, Q)

    if affine:
        row(0, grid[..., 0])
        row(1, grid[..., 1])
    else:
        qw = row(2).clamp_min_(1e-6)
        torch.div(row(0), qw, out=grid[..., 0])
        torch.div(row(1), qw, out=grid[..., 1])
    return grid


def _grid_square(M32: torch.Tensor, axes: tuple[torch.Tensor, torch.Tensor], affine: bool
                 ) -> torch.Tensor:
    """:func:`_grid` on a square grid of offsets (``axes`` = (xs, ys), (S,) each), all rows
    of M at once: coordinate r of offset (xs[x], ys[y]) is ``(m_r0 xs[x] + m_r1 ys[y]) +
    m_r2`` (the products once per column and per row), then divided by the clamped w
    unless affine. The same float32 operations in the same order as the row-by-row form,
    so the same bits.

    The coordinates are computed planar, (n, 2, S*S) (contiguous, vectorised), and returned
    as an (n, S*S, 2) view of it: ``grid_sample`` reads a strided grid, and this is faster
    than writing the interleaved grid."""
    xs, ys = axes
    n, side = M32.shape[0], xs.shape[0]
    nr = 2 if affine else 3  # w = 1 exactly for an affine map
    m = M32[:, :nr, :, None]  # (n, nr, 3, 1)
    v = torch.add((m[:, :, 0] * xs)[:, :, None, :], (m[:, :, 1] * ys)[:, :, :, None])
    v += m[:, :, 2, :, None]  # (n, nr, S_y, S_x)
    if not affine:
        v = torch.div(v[:, :2], v[:, 2:].clamp_min_(1e-6))
    return v.view(n, 2, side * side).transpose(1, 2)


def _sample(image: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear samples (n, Q) float32 of one (H, W) image at ``grid`` (n, Q, 2) (zeros
    outside; ``align_corners=True``)."""
    out = F.grid_sample(image[None, None], grid[None], mode="bilinear", padding_mode="zeros",
                        align_corners=True)  # (1, 1, n, Q)
    return out[0, 0]


def to_frame(H: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(J, 2) points mapped by (J, 3, 3) homographies (w clamped positive; elementwise, so a
    point's result does not depend on the others)."""
    X, Y, W = project(H, x[:, 0], x[:, 1])
    W = W.clamp_min(1e-12)
    return torch.stack([X / W, Y / W], dim=1)


def frame_jacobian(H_inv: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """(n, 2, 2) float64 Jacobians of the maps ``H_inv`` (n, 3, 3) (frame -> image pixels) at
    the frame points ``p`` (n, 2): image pixels per frame pixel."""
    xh = H_inv[:, :, :2] @ p[:, :, None] + H_inv[:, :, 2:]  # (n, 3, 1)
    w = xh[:, 2:, :]
    x = xh[:, :2, :] / w
    return (H_inv[:, :2, :2] - x * H_inv[:, 2:, :2]) / w


def local_scale(J: torch.Tensor) -> torch.Tensor:
    """(n,) image pixels per frame pixel, sqrt |det J|, of the (n, 2, 2) Jacobians ``J``."""
    return torch.linalg.det(J).abs().sqrt()
