"""Batched homography maths for MOP (float64), for numpy and torch alike; ``(x, y)`` pixels, ``H``
maps ``x`` to ``H [x, y, 1]``. Inverses are adjugates: they never divide, so no infinities."""

from __future__ import annotations

import math
import sys

import numpy as np


def array_module(a):
    """``numpy`` for numpy arrays (and scalars), ``torch`` for torch tensors."""
    if isinstance(a, np.ndarray):
        return np
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(a, torch.Tensor):
        return torch
    return np


def zeros(like, shape: tuple[int, ...]):
    """float64 zeros of ``shape`` of the same kind (and torch device) as ``like``."""
    if isinstance(like, np.ndarray):
        return np.zeros(shape)
    return like.new_zeros(shape, dtype=like.dtype)


def normalise_points(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalisation of ``(B, M, 2)`` points: ``(T (B, 3, 3), pts_n = T pts)``, centroid 0
    and mean distance ``sqrt(2)``."""
    scale, centroid, normalised = _normalised(pts)
    T = zeros(pts, (pts.shape[0], 3, 3))
    T[:, 0, 0] = scale
    T[:, 1, 1] = scale
    T[:, :2, 2] = -scale[:, None] * centroid[:, 0, :]
    T[:, 2, 2] = 1.0
    return T, normalised


def _normalised(pts: np.ndarray):
    """``(scale (B,), centroid (B, 1, 2), normalised points)`` of :func:`normalise_points`."""
    xp = array_module(pts)
    m = pts.shape[1]
    centroid = pts.sum(axis=1, keepdims=True) / m
    centred = pts - centroid
    mean_dist = xp.sqrt((centred**2).sum(-1)).sum(axis=1) / m
    scale = math.sqrt(2.0) / xp.clip(mean_dist, 1e-12, None)
    return scale, centroid, centred * scale[:, None, None]


# adj(H) = H[_ADJ[0]] * H[_ADJ[1]] - H[_ADJ[2]] * H[_ADJ[3]] entrywise, over the row-major
# entries a..i of H: e.g. adj[0, 0] = e * i - f * h.
_ADJ = np.array([[4, 2, 1, 5, 0, 2, 3, 1, 0],
                 [8, 7, 5, 6, 8, 3, 7, 6, 4],
                 [5, 1, 2, 3, 2, 0, 4, 0, 1],
                 [7, 8, 4, 8, 6, 5, 6, 7, 3]])
_ADJ_FLAT = _ADJ.reshape(-1)
_ADJ_ON_DEVICE: dict = {}


def adjugate(H: np.ndarray) -> np.ndarray:
    """Adjugate of ``(..., 3, 3)`` matrices (``adj(H) H = det(H) I``), all nine entries in a few
    whole-array operations (each a kernel launch on a GPU)."""
    lead = tuple(H.shape[:-2])
    idx = _ADJ_FLAT
    if not isinstance(H, np.ndarray):
        idx = _ADJ_ON_DEVICE.get(H.device)
        if idx is None:
            idx = _ADJ_ON_DEVICE[H.device] = array_module(H).as_tensor(_ADJ_FLAT,
                                                                        device=H.device)
    g = H.reshape(lead + (9,))[..., idx].reshape(lead + (4, 9))  # one gather for all factors
    adj = g[..., 0, :] * g[..., 1, :] - g[..., 2, :] * g[..., 3, :]
    return adj.reshape(H.shape)


def normalise_scale(H: np.ndarray) -> np.ndarray:
    """Scale ``(..., 3, 3)`` homographies to unit Frobenius norm (keeps the sign)."""
    xp = array_module(H)
    norm = xp.sqrt((H**2).sum(axis=(-2, -1), keepdims=True))
    return H / xp.clip(norm, 1e-300, None)


def _dlt_system(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The DLT system ``A`` ``(B, 2M, 9)`` with ``A h = 0`` for ``d ~ H s`` (two rows per point)."""
    xp = array_module(s)
    B, M, _ = s.shape
    if xp is np:
        # Filled by blocks (numpy: fewer calls than the stacks below, the same entries).
        A = np.zeros((B, M, 2, 9))
        nd = -d
        A[:, :, 0, 0:2] = s
        A[:, :, 0, 2] = 1.0
        A[:, :, 1, 3:5] = s
        A[:, :, 1, 5] = 1.0
        A[:, :, 0, 6:8] = nd[..., 0:1] * s  # -u x, -u y
        A[:, :, 1, 6:8] = nd[..., 1:2] * s  # -v x, -v y
        A[:, :, :, 8] = nd
        return A.reshape(B, 2 * M, 9)
    # Stacked rather than assigned entry by entry: a few whole-array operations (a kernel
    # launch each on a device).
    x, y, u, v = s[..., 0], s[..., 1], d[..., 0], d[..., 1]
    one, zero = xp.ones_like(x), xp.zeros_like(x)
    nu, nv = -u, -v
    even = xp.stack([x, y, one, zero, zero, zero, nu * x, nu * y, nu], axis=-1)
    odd = xp.stack([zero, zero, zero, x, y, one, nv * x, nv * y, nv], axis=-1)
    return xp.stack([even, odd], axis=2).reshape(B, 2 * M, 9)


def dlt(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised DLT of ``(B, M, 2)`` point sets (``M >= 4``): ``(H, sv)``, ``dst ~ H src`` with
    unit Frobenius norm, ``sv`` the smallest singular value of the minimal system (degeneracy test)."""
    B, M, _ = src.shape
    T1, s = normalise_points(src)
    T2, d = normalise_points(dst)
    A = _dlt_system(s, d)
    if M == 4:
        _, sv, vh = np.linalg.svd(A, full_matrices=True)
        sv8 = sv[:, 7]
    else:
        # Least squares: the eigen-decomposition of A^T A (9 x 9) is cheaper than an SVD of
        # the tall 2M x 9 system; its eigenvalues are the squared singular values.
        evals, evecs = np.linalg.eigh(np.swapaxes(A, 1, 2) @ A)
        vh = np.swapaxes(evecs, 1, 2)[:, ::-1]
        sv8 = np.sqrt(np.maximum(evals[:, 1], 0.0))
    Hn = vh[:, -1].reshape(B, 3, 3)
    H = adjugate(T2) @ Hn @ T1
    return normalise_scale(H), sv8


def _basis_map(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projective map ``(P diag(lam), lam, det(P))`` sending the canonical basis and (1, 1, 1) to
    ``p`` ``(B, 4, 3)``."""
    P = array_module(p).swapaxes(p[:, :3], 1, 2)  # columns p0, p1, p2
    adj = adjugate(P)
    lam = (adj @ p[:, 3, :, None])[..., 0]  # det(P) * P^-1 p3
    det = P[:, 0, 0] * adj[:, 0, 0]  # the 3-term sum written out (same order, same bits)
    det += P[:, 0, 1] * adj[:, 1, 0]
    det += P[:, 0, 2] * adj[:, 2, 0]
    return P * lam[:, None, :], lam, det


def four_point(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form homographies ``(B, 3, 3)`` of 4-point samples (the minimal DLT's, no SVD), with
    the quasi-affine signs ``(B, 4)`` of the samples forward and backward (App. A.3)."""
    xp = array_module(src)
    one = xp.ones_like(src[..., :1])
    A, lam, det_p = _basis_map(xp.concatenate([src, one], axis=2))
    Bm, mu, det_q = _basis_map(xp.concatenate([dst, one], axis=2))
    H = normalise_scale(Bm @ adjugate(A))
    s_lam, s_mu = xp.sign(lam), xp.sign(mu)
    s_det_a = xp.sign(det_p) * s_lam[:, 0] * s_lam[:, 1] * s_lam[:, 2]  # sign det(A)
    s_det_b = xp.sign(det_q) * s_mu[:, 0] * s_mu[:, 1] * s_mu[:, 2]  # sign det(B)
    sign_fwd = xp.empty_like(src[..., 0])
    sign_inv = xp.empty_like(src[..., 0])
    sign_fwd[:, :3] = s_det_a[:, None] * s_mu * s_lam
    sign_fwd[:, 3] = s_det_a * xp.sign(det_q) * xp.sign(det_p)
    sign_inv[:, :3] = (s_det_a * s_det_b)[:, None] * s_lam * s_mu
    sign_inv[:, 3] = s_det_a * s_det_b * xp.sign(det_p) * xp.sign(det_q)
    return H, sign_fwd, sign_inv


def dlt_singular_value(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Smallest singular value ``(B,)`` of the minimal DLT system of ``(B, 4, 2)`` samples (the
    paper keeps hypotheses above 0.05)."""
    xp = array_module(src)
    A = _dlt_system(_normalised(src)[2], _normalised(dst)[2])
    evals = xp.linalg.eigvalsh(A @ xp.swapaxes(A, 1, 2))
    return xp.sqrt(xp.clip(evals[:, 0], 0.0, None))


def project(H: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Apply ``(K, 3, 3)`` homographies to ``(N, 2)`` or ``(K, N, 2)`` points: ``(x, y, w)`` each
    ``(K, N)``, ``w`` before division (its sign feeds the quasi-affinity test)."""
    # Explicit broadcasting: a matmul with inner dimension 2-3 is slower.
    h = H.reshape(tuple(H.shape[:-2]) + (9, 1))
    X, Y = pts[..., 0], pts[..., 1]
    w = h[..., 6, :] * X
    w += h[..., 7, :] * Y
    w += h[..., 8, :]
    x = h[..., 0, :] * X
    x += h[..., 1, :] * Y
    x += h[..., 2, :]
    y = h[..., 3, :] * X
    y += h[..., 4, :] * Y
    y += h[..., 5, :]
    safe_w = array_module(w).where(w == 0, 1e-300, w)
    x /= safe_w
    y /= safe_w
    return x, y, w


def transfer_error_sq(H: np.ndarray, src: np.ndarray, dst: np.ndarray, out: tuple | None = None):
    """``(e, w)`` ``(K, N)``: squared transfer error ``|H(src) - dst|^2`` (same bits as
    :func:`project`, in place) and ``w``; ``e`` is inf/nan where ``w == 0``. ``out``: reusable work
    arrays."""
    xp = array_module(H)
    h = H.reshape(tuple(H.shape[:-2]) + (9, 1))
    X, Y = src[..., 0], src[..., 1]
    if out is None:
        w = h[..., 6, :] * X
        x, y, tmp = xp.empty_like(w), xp.empty_like(w), xp.empty_like(w)
    else:
        x, w, y, tmp = out
        xp.multiply(h[..., 6, :], X, out=w)
    xp.multiply(h[..., 7, :], Y, out=tmp)
    w += tmp
    w += h[..., 8, :]
    for v, r, c in ((x, 0, 0), (y, 3, 1)):  # (x or y of H(src) - dst)^2, in place
        xp.multiply(h[..., r, :], X, out=v)
        xp.multiply(h[..., r + 1, :], Y, out=tmp)
        v += tmp
        v += h[..., r + 2, :]
        v /= w
        v -= dst[..., c]
        v *= v
    x += y
    return x, w


def one_way_inside(h, X, Y, x2, y2, t2: float, out: tuple | None = None):
    """Division-free one-way inlier test ``(K, N)``: ``w > 0`` and ``|u - x2 w|^2 + |v - y2 w|^2 <=
    t2 w^2`` for sign-scaled ``h`` ``(K, 9, 1)``; ``out`` reuses work arrays."""
    xp = array_module(h)
    if out is None:
        W = h[:, 6] * X
        U, V, T = xp.empty_like(W), xp.empty_like(W), xp.empty_like(W)
        ok, tmp = W > 0, W > 0  # bool work arrays (overwritten below)
    else:
        W, U, V, T, ok, tmp = out
        xp.multiply(h[:, 6], X, out=W)
    xp.multiply(h[:, 7], Y, out=T)
    W += T
    W += h[:, 8]
    xp.multiply(h[:, 0], X, out=U)
    xp.multiply(h[:, 1], Y, out=T)
    U += T
    U += h[:, 2]
    xp.multiply(W, x2, out=T)
    U -= T
    xp.multiply(h[:, 3], X, out=V)
    xp.multiply(h[:, 4], Y, out=T)
    V += T
    V += h[:, 5]
    xp.multiply(W, y2, out=T)
    V -= T
    U *= U
    V *= V
    U += V
    xp.greater(W, 0, out=ok)
    W *= W
    W *= t2
    xp.less_equal(U, W, out=tmp)
    ok &= tmp
    return ok


def to_unit_h33(H: np.ndarray) -> np.ndarray:
    """Scale homographies to ``H[2, 2] == 1`` where that entry is not tiny, else to unit norm."""
    H = normalise_scale(np.asarray(H, dtype=np.float64))
    h33 = H[..., 2:3, 2:3]
    ok = np.abs(h33) > 1e-8
    return np.where(ok, H / np.where(ok, h33, 1.0), H * np.where(h33 < 0, -1.0, 1.0))


def triangle_orientations(pts: np.ndarray) -> np.ndarray:
    """Signed doubled areas ``(B, 4)`` of the four triangles of ``(B, 4, 2)`` quadruples (MOP*'s
    reflection check, App. D)."""
    out = np.empty(pts.shape[:1] + (4,))
    for t, (i, j, k) in enumerate(((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))):
        a = pts[:, j] - pts[:, i]
        b = pts[:, k] - pts[:, i]
        out[:, t] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out
