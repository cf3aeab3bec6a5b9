"""The array inputs of :func:`.ncc.refine_pair`: shape checks, float64 numpy, and the
homography pairs it searches (the filter's, oriented; the keypoint-frame base pair)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .warping import ImageStack

#: an image argument of :func:`.ncc.refine_pair`: (H, W) numpy or torch, or one image per match.
ImageInput = np.ndarray | torch.Tensor | ImageStack
#: an array argument: numpy, torch or anything ``np.asarray`` takes.
ArrayInput = np.ndarray | torch.Tensor


def _as_array(name: str, value: object, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        tail = ", ".join(map(str, shape_tail))
        raise ValueError(f"{name} must have shape (N, {tail}), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} rows, expected {n}")
    return arr


def normalise_signs(homs: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Homographies are defined up to scale, sign included: flip each A (B) so that the
    homogeneous w of A x1 (B x2) is positive, as the patch sampling expects."""
    homs = homs.copy()
    for side, p in ((0, p1), (1, p2)):
        w = np.einsum("nj,nj->n", homs[:, side, 2, :2], p) + homs[:, side, 2, 2]
        homs[w < 0, side] *= -1.0
    return homs


def base_pairs(n: int, affine1: np.ndarray | None, affine2: np.ndarray | None) -> np.ndarray:
    """(N, 2, 3, 3) base pair: identity, or the inverse keypoint affine frames scaled to keep
    about one common-frame pixel per image pixel."""
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
