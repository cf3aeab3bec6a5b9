"""MiHo and VSAC splits of a homography into two middle homographies (paper Sec. 3.2, App. B, C),
and the rotation fix that pre-aligns image 2 by a multiple of 90 degrees."""

from __future__ import annotations

import functools

import numpy as np

from .compiled import miho as kernels
from .problem import Problem

_ROTATION_Z = 3.0  # paired z-score a non-identity pre-alignment needs over the identity


@functools.cache
def _linear_parts(reflections: bool) -> tuple[np.ndarray, ...]:
    out = []
    for mirror in (False, True) if reflections else (False,):
        for k in range(4):
            a = k * np.pi / 2
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).round(12)
            if mirror:
                R = R @ np.diag([-1.0, 1.0])
            R.flags.writeable = False
            out.append(R)
    return tuple(out)


@functools.lru_cache(maxsize=64)
def _all_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(n, 1)
    i.flags.writeable = False
    j.flags.writeable = False
    return i, j


def _candidate_transforms(x2: np.ndarray, reflections: bool) -> list[np.ndarray]:
    """3x3 affine maps of image 2: rotations by k*90 degrees about the centroid, optionally mirrored; identity first."""
    c = x2.mean(axis=0)
    out = []
    for R in _linear_parts(reflections):
        G = np.eye(3)
        G[:2, :2] = R
        G[:2, 2] = c - R @ c
        out.append(G)
    return out


def apply_affine(G: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 affine map ``G`` to ``(N, 2)`` points."""
    return pts @ G[:2, :2].T + G[:2, 2]


def _differences(x: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``(2, P)`` differences ``x[i] - x[j]``, gathered per coordinate (cheaper than 2-float rows)."""
    xt = np.ascontiguousarray(x.T)
    return np.take(xt, i, axis=1) - np.take(xt, j, axis=1)


def _norms(d: np.ndarray) -> np.ndarray:
    """``(P,)`` lengths of ``d``, the same bits as ``sqrt((d.T**2).sum(1))``."""
    sq = d[0] * d[0]
    sq += d[1] * d[1]
    return np.sqrt(sq)


def choose_rotation(x1: np.ndarray, x2: np.ndarray, rng: np.random.Generator, *,
                    pairs: int = 20000, reflections: bool = False,
                    compiled: bool = True) -> tuple[np.ndarray, int, int]:
    """The rotation fix's ``(G, index, score)`` (``x2' = G x2``; index 0-3 rotations, 4-7 mirrored):
    the identity stays unless another candidate wins by three standard deviations on the same pairs.
    """
    N = len(x1)
    if N < 2:
        return np.eye(3), 0, 0
    if pairs == 0 or pairs >= N * (N - 1) // 2:
        i, j = _all_pairs(N)
    else:
        i = rng.integers(0, N, pairs)
        j = rng.integers(0, N, pairs)
        keep = i != j
        i, j = i[keep], j[keep]
    dx1 = _differences(x1, i, j)  # (2, P): x and y rows
    dx2 = _differences(x2, i, j)
    d1 = _norms(dx1)
    d2 = _norms(dx2)  # invariant to the candidates (isometries)
    lo, hi = np.minimum(d1, d2) - 1e-9, np.maximum(d1, d2) + 1e-9
    cands = _candidate_transforms(x2, reflections)
    if compiled:
        rows = np.ascontiguousarray(np.stack([G[:2, :2] for G in cands]))
        scores, differ = kernels.rotation_counts(np.ascontiguousarray(dx1),
                                                 np.ascontiguousarray(dx2), lo, hi, rows)
        return _pick_rotation(cands, scores, differ)
    # m_i - m_j = (dx1 + R dx2) / 2: translations cancel, only the linear part matters. Its
    # entries are 0 or +-1, so each coordinate is dx1 + or - one coordinate of dx2 (the zero
    # term only changes the sign of a zero, which squaring removes): 4 squares per axis
    # serve all the candidates.
    squares: dict[tuple[int, float, float], np.ndarray] = {}

    def square(axis: int, r: np.ndarray) -> np.ndarray:
        """``(dx1[:, axis] + r[0] dx2[:, 0] + r[1] dx2[:, 1])^2`` for a row ``r`` of R."""
        key = (axis, float(r[0]), float(r[1]))
        if key not in squares:
            assert sorted(np.abs(r)) == [0.0, 1.0], "rotations by multiples of 90 degrees"
            v = dx1[axis] + (r[0] * dx2[0] if r[0] else r[1] * dx2[1])
            squares[key] = v * v
        return squares[key]

    dm = np.stack([np.sqrt(square(0, G[0, :2]) + square(1, G[1, :2])) for G in cands]) / 2
    inside = (dm >= lo) & (dm <= hi)  # (C, P)
    scores = np.count_nonzero(inside, axis=1)
    # Keep the identity unless a candidate beats it clearly on the same pairs (paired
    # z-score above _ROTATION_Z): where few matches are correct, pairs of outliers decide
    # the counts and their noise would otherwise turn an upright pair (with mostly random
    # matches, a mirrored frame can win and lose every match).
    # The paired differences are -1, 0 or 1: their sum of squares counts the pairs that differ.
    return _pick_rotation(cands, scores, np.count_nonzero(inside != inside[0], axis=1))


def _pick_rotation(cands: list[np.ndarray], scores: np.ndarray,
                   differ: np.ndarray) -> tuple[np.ndarray, int, int]:
    """:func:`choose_rotation`'s choice from the candidates' counts and disagreeing pairs."""
    spread = np.sqrt(np.maximum(differ, 1))
    z = (scores - scores[0]) / spread
    clear = np.flatnonzero(z > _ROTATION_Z)
    best = int(clear[np.argmax(scores[clear])]) if len(clear) else 0
    return cands[best], best, int(scores[best])


def build_problem(x1: np.ndarray, x2: np.ndarray, miho: bool, full_match: bool = False) -> Problem:
    """The RANSAC problem of MOP (one half) or MOP+MiHo (two, via the midpoint); ``full_match``
    doubles the half-match errors so the thresholds bound the full match as for MOP."""
    if not miho:
        return Problem(src=(x1,), dst=(x2,), spread=(x1, x2), x1=x1, x2=x2)
    m = (x1 + x2) / 2
    return Problem(src=(x1, m), dst=(m, x2), spread=(x1, x2, m), x1=x1, x2=x2,
                   error_scale=2.0 if full_match else 1.0)


def sqrt_split(H: np.ndarray, tol: float = 1e-6) -> np.ndarray | None:
    """VSAC half homography ``H_v`` with ``H_v H_v ~ H``, or None without an accurate real root
    (180-degree rotation, reflection)."""
    from scipy.linalg import sqrtm

    Hs = H / np.cbrt(np.linalg.det(H)) if np.linalg.det(H) != 0 else None
    if Hs is None or not np.all(np.isfinite(Hs)):
        return None
    # det(Hs) = 1 > 0 now (the real cube root keeps the sign that makes it positive).
    with np.errstate(all="ignore"):
        try:
            Hv = sqrtm(Hs)
        except (ValueError, np.linalg.LinAlgError):
            return None
    Hv = np.asarray(Hv)
    if not np.all(np.isfinite(Hv)):
        return None
    if np.iscomplexobj(Hv):
        if np.abs(Hv.imag).max() > tol * max(np.abs(Hv.real).max(), 1e-12):
            return None
        Hv = Hv.real
    resid = np.abs(Hv @ Hv - Hs).max() / np.abs(Hs).max()
    return Hv if resid <= tol else None
