"""Batched homography patch sampling with torch (bilinear, pixel centres at integers): a patch
around common-frame ``c`` reads the image at ``H^-1 (c + w)``. On the CPU a job's samples never
depend on the other jobs of the call, so nothing runs across jobs (no GEMM, no reduction)."""

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
    """Image as a float32 ``(H, W)`` tensor on ``device``; uint8 is divided by 255, float used as is."""
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
    """Several images for one batch of jobs, job j reading image ``index[j]`` only (no padded copy),
    so one batched call serves many pairs."""

    images: tuple
    slot_sizes: torch.Tensor
    index: torch.Tensor

    @classmethod
    def build(cls, images: list[torch.Tensor], index: IndexLike, device: torch.device) -> ImageStack:
        """Hold ``(H, W)`` float32 tensors on ``device``; ``index`` ``(J,)`` picks each job's image."""
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
    """The images of the jobs ``rows``: the stack's rows, or a plain image that serves every job."""
    return image.rows(rows) if isinstance(image, ImageStack) else image


def image_arrays(image: torch.Tensor | ImageStack, n: int) -> tuple[list[np.ndarray], np.ndarray]:
    """The images as float32 numpy views and each job's index into them, for the compiled kernels."""
    if isinstance(image, ImageStack):
        return ([im.contiguous().numpy() for im in image.images],
                image.index.cpu().numpy().astype(np.int64))
    return [image.contiguous().numpy()], np.zeros(n, np.int64)


def offset_grid(radius: int, device: torch.device, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Integer offsets ``(P, 2)`` (x, y) of a (2r+1)^2 square, row-major, so ``(..., P)`` reshapes to ``[y, x]``."""
    r = torch.arange(-radius, radius + 1, device=device, dtype=dtype)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def invert_homographies(H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched 3x3 inverse by the adjugate: ``(H_inv, valid)``; singular or non-finite get the identity."""
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
    """Homogeneous ``H [x; y; 1]`` by elementwise products (a matmul rounds differently with batch size)."""
    shape = (H.shape[0], 3) + (1,) * (x.ndim - 1)  # (J, 3, 1, ...) against (J, 1, ...)
    h0, h1, h2 = (H[..., c].reshape(shape) for c in range(3))
    xyw = h0 * x[:, None] + h1 * y[:, None] + h2
    return xyw[:, 0], xyw[:, 1], xyw[:, 2]


def apply_homographies(H: torch.Tensor, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Map ``pts`` ``(J, P, 2)`` by ``H`` ``(J, 3, 3)``: ``(mapped, ok)``; points behind the line at
    infinity get ``ok=False``."""
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
    """Sample square patches of the image around common-frame centres.

    ``H_inv`` ``(J, 3, 3)`` maps the common frame to image pixels; ``centres`` ``(J, 2)``;
    ``offsets`` ``(K, P, 2)`` shared or ``(J, K, P, 2)`` per job. Returns (values ``(J, K, P)``
    float32, inside ``(J,)``: every shape's corners map in front of the camera and into the image).
    The centre is mapped in float64, offsets relative to it in float32 (sub-1e-3 pixel, far
    cheaper), and a job's values are bitwise the same whatever the other jobs."""
    values, good = sample_values(image, H_inv, centres, offsets)
    return values, patch_inside(image, H_inv, centres, offsets) & good


def patch_inside(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    offsets: torch.Tensor,
) -> torch.Tensor:
    """The inside test of :func:`sample_patches` alone, ``(J,)`` bool."""
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
    """The values of :func:`sample_patches` (same bits) without the inside test; ``good``: the
    centre maps in front of the camera."""
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
    """Per job, the 3x3 map from common-frame offsets to ``grid_sample`` coordinates of its own
    image, and whether the centre maps in front of the camera."""
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
    """``(xs, ys)`` when the offsets form a row-major square grid, else None."""
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
    """``grid_sample`` coordinates ``(n, Q, 2)`` float32 by elementwise float32 operations (no GEMM,
    so a job's result does not depend on n); ``affine`` skips the exact division by w = 1."""
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
    """:func:`_grid` on a square grid with the products once per column and row: the same operations
    in the same order, so the same bits. Computed planar and returned as a strided view (faster)."""
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
    """Bilinear samples ``(n, Q)`` of one image at ``grid`` (zeros outside, ``align_corners=True``)."""
    out = F.grid_sample(image[None, None], grid[None], mode="bilinear", padding_mode="zeros",
                        align_corners=True)  # (1, 1, n, Q)
    return out[0, 0]


def to_frame(H: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``(J, 2)`` points mapped by ``(J, 3, 3)`` homographies (w clamped positive; elementwise)."""
    X, Y, W = project(H, x[:, 0], x[:, 1])
    W = W.clamp_min(1e-12)
    return torch.stack([X / W, Y / W], dim=1)


def frame_jacobian(H_inv: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Jacobians ``(n, 2, 2)`` of ``H_inv`` (frame -> image) at frame points ``p``: image px per frame px."""
    xh = H_inv[:, :, :2] @ p[:, :, None] + H_inv[:, :, 2:]  # (n, 3, 1)
    w = xh[:, 2:, :]
    x = xh[:, :2, :] / w
    return (H_inv[:, :2, :2] - x * H_inv[:, 2:, :2]) / w


def local_scale(J: torch.Tensor) -> torch.Tensor:
    """(n,) image pixels per frame pixel, sqrt |det J|, of the (n, 2, 2) Jacobians ``J``."""
    return torch.linalg.det(J).abs().sqrt()
