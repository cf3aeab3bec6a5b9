"""Restoring matches the filter removed when the scene proves them (pure numpy).

A planar-homography filter is weakest on wide-baseline pairs: few matches, strong perspective,
no plane with enough support, so it drops correct matches and whole correct pairs. The match
check's global estimate can give them back, but an epipolar test alone never may: repeated
structure puts wrong matches exactly on the epipolar line (a facade's windows along a
horizontal baseline). A removed match comes back only when

1. its distance to its epipolar line under the estimate is within :data:`EPIPOLAR_SHARE` of the
   check's threshold (a match the filter removed needs more proof than one it kept), and
2. a third image confirms its depth: one of its keypoints is matched, by a match the check
   kept, to a keypoint of a third trusted image, and the point triangulated from the removed
   match reprojects there within the threshold, in front of the camera; that third image must
   see a depth error along the confirmed keypoint's ray at least
   :data:`MIN_DEPTH_SENSITIVITY` times as large as the pair's other image does, so a match
   displaced along its epipolar line (the repeated-structure error) cannot pass unseen;
3. it joins no two tracks of the kept matches that hold a keypoint of the same image.

Conventions as :mod:`.match_check`: ``cam_from_world`` poses, normalised ``rays``, focal
lengths in pixels.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..geometry import essential, relative_pose, symmetric_epipolar_distance
from ..types import Pair, Pose

#: The third image's pixels per unit depth along the confirmed ray, over the pair's other
#: image's: a match displaced by ``d`` px along its epipolar line moves the reprojection in the
#: third image by at least half of ``d``.
MIN_DEPTH_SENSITIVITY = 0.5

#: The share of the check's threshold a restored match must lie within of its epipolar line.
EPIPOLAR_SHARE = 0.5

_SHIFT = np.int64(32)


def restore_matches(candidates: Mapping[Pair, np.ndarray], kept: Mapping[Pair, np.ndarray],
                    rays: Mapping[int, np.ndarray], focal: Mapping[int, float], poses: Mapping[int, Pose],
                    trusted: frozenset[int] | set[int], threshold: float) -> dict[Pair, np.ndarray]:
    """Which ``candidates`` (pair -> int ``(R, 2)`` keypoint indices removed by the filter) the
    estimate and the ``kept`` matches (pair -> ``(M, 2)``) prove, the check's ``threshold`` (px)
    given; pair -> bool ``(R,)``, only pairs of two ``trusted`` images with any restored."""
    ends = _kept_ends(kept, trusted)
    cams = _Cameras.of(poses, focal)
    out: dict[Pair, np.ndarray] = {}
    for (i, j), m in sorted(candidates.items()):
        if i not in trusted or j not in trusted or not len(m):
            continue
        ok = proven(np.asarray(m, np.int64), i, j, ends, rays, cams, threshold, EPIPOLAR_SHARE * threshold)
        if ok.any():
            out[(i, j)] = ok
    return _track_consistent(out, candidates, ends)


def _track_consistent(proven_: dict[Pair, np.ndarray], candidates: Mapping[Pair, np.ndarray], ends
                      ) -> dict[Pair, np.ndarray]:
    """``proven_`` less the matches that would join two tracks of the kept matches (or a
    keypoint to a track) holding a keypoint of the same image: a match between two points
    that one image sees at nearly the same place passes every geometric test, and the track it
    makes is wrong. Judged in pair and row order, each accepted match joining its tracks. Only
    the tracks of the proven matches' keypoints are walked (:func:`_track`), not the whole graph."""
    if not proven_:
        return {}
    comp_of: dict[int, int] = {}  # a walked keypoint's key -> its track (the track's smallest key)
    comp_images: dict[int, set[int]] = {}
    parent: dict[int, int] = {}

    def root(c: int) -> int:
        while parent.get(c, c) != c:
            c = parent[c]
        return c

    def track_of(image: int, kp: int) -> int:
        key = (image << int(_SHIFT)) | kp
        if key not in comp_of:
            nodes = _track(key, ends)
            c = min(nodes)
            comp_of.update(dict.fromkeys(nodes, c))
            comp_images[c] = {k >> int(_SHIFT) for k in nodes}
        return root(comp_of[key])

    out = {}
    for (i, j), ok in proven_.items():
        m = np.asarray(candidates[(i, j)], np.int64)
        for r in np.flatnonzero(ok):
            a, b = track_of(i, int(m[r, 0])), track_of(j, int(m[r, 1]))
            if a != b and comp_images[a] & comp_images[b]:
                ok[r] = False
            elif a != b:
                parent[b] = a
                comp_images[a] |= comp_images.pop(b)
        if ok.any():
            out[(i, j)] = ok
    return out


def _track(key: int, ends: tuple[np.ndarray, np.ndarray, np.ndarray]) -> set[int]:
    """The keys (``image << 32 | keypoint``) of the kept matches' track holding ``key``, found
    by a breadth-first walk over :func:`_kept_ends`' sorted edges; ``{key}`` for a keypoint in
    no kept match."""
    starts, end_img, end_kp = ends
    seen = {key}
    frontier = np.array([key], np.int64)
    while frontier.size:
        edge, _ = _edges_from(starts, frontier)
        reached = set(((end_img[edge].astype(np.int64) << _SHIFT) | end_kp[edge]).tolist()) - seen
        seen |= reached
        frontier = np.fromiter(reached, np.int64, len(reached))
    return seen


def proven(m: np.ndarray, i: int, j: int, ends: tuple[np.ndarray, np.ndarray, np.ndarray],
           rays: Mapping[int, np.ndarray], cams: _Cameras, threshold: float, epipolar_px: float) -> np.ndarray:
    """bool ``(R,)``: the matches ``m`` of pair ``(i, j)`` within ``epipolar_px`` of their
    epipolar line and confirmed by a third image within ``threshold`` px (:func:`_kept_ends`'
    index ``ends``)."""
    poses, focal = cams.poses, cams.focal
    x1, x2 = rays[i][m[:, 0]], rays[j][m[:, 1]]
    scale = float(np.sqrt(focal[i] * focal[j]))
    d = symmetric_epipolar_distance(essential(relative_pose(poses[i], poses[j])), x1, x2) * scale
    ok = np.zeros(len(m), bool)
    close = np.flatnonzero(d <= epipolar_px)
    if not close.size:
        return ok
    X, depth_i, depth_j = _midpoints(poses[i], x1[close], poses[j], x2[close])
    front = (depth_i > 0) & (depth_j > 0)
    close, X = close[front], X[front]
    for side, (own, other) in enumerate(((i, j), (j, i))):
        left = ~ok[close]
        if not left.any():
            break
        rows = close[left]
        ok[rows[_confirmed(X[left], own, other, m[rows, side], ends, rays, cams, threshold)]] = True
    return ok


def _kept_ends(kept: Mapping[Pair, np.ndarray], trusted) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kept matches between trusted images as directed edges sorted by their start:
    (int64 start keys ``image << 32 | keypoint``, int32 end images, int32 end keypoints)."""
    used = [(i, j, m) for (i, j), m in kept.items() if i in trusted and j in trusted and len(m)]
    total = 2 * sum(len(m) for _, _, m in used)
    s = np.empty(total, np.int64)
    end_img = np.empty(total, np.int32)
    end_kp = np.empty(total, np.int32)
    at = 0
    for i, j, m in used:  # filled in place: at a million matches the pieces and their concatenation cost GBs
        n = len(m)
        a, b = np.asarray(m[:, 0], np.int64), np.asarray(m[:, 1], np.int64)
        s[at:at + n], s[at + n:at + 2 * n] = (np.int64(i) << _SHIFT) | a, (np.int64(j) << _SHIFT) | b
        end_img[at:at + n], end_img[at + n:at + 2 * n] = j, i
        end_kp[at:at + n], end_kp[at + n:at + 2 * n] = b, a
        at += 2 * n
    order = np.argsort(s, kind="stable")
    return s[order], end_img[order], end_kp[order]


def _confirmed(X: np.ndarray, own: int, other: int, kps: np.ndarray, ends, rays, cams: _Cameras,
               threshold: float) -> np.ndarray:
    """bool ``(n,)``: points ``X`` ``(n, 3)`` of matches whose keypoint ``kps`` in image ``own``
    a kept match links to a third image that sees ``X`` within ``threshold`` px, with enough
    depth sensitivity against image ``other`` (every link at once)."""
    starts, end_img, end_kp = ends
    edge, counts = _edges_from(starts, (np.int64(own) << _SHIFT) | kps)
    ok = np.zeros(len(X), bool)
    if not counts.any():
        return ok
    which = np.repeat(np.arange(len(X)), counts)
    third, third_kp = end_img[edge], end_kp[edge]
    at, posed = cams.index(third)
    use = posed & (third != other)
    if not use.any():
        return ok
    which, third, third_kp, at = which[use], third[use], third_kp[use], at[use]
    ray_own = _world_rays(cams.poses[own], rays[own][kps])
    R_other, t_other = (np.asarray(a, np.float64) for a in cams.poses[other])
    _, sens_other = _reprojection(R_other, t_other.reshape(3), X, ray_own, None)
    err, sens = _reprojection(cams.R[at], cams.t[at], X[which], ray_own[which], _gather(rays, third, third_kp))
    f = cams.f[at]
    with np.errstate(over="ignore", invalid="ignore"):
        good = (err * f <= threshold) & (sens * f >= MIN_DEPTH_SENSITIVITY * sens_other[which] * cams.focal[other])
    ok[which[good]] = True
    return ok


def _edges_from(starts: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of the sorted ``starts`` equal to each of ``keys``, in key order, and their
    number per key."""
    lo, hi = np.searchsorted(starts, keys, "left"), np.searchsorted(starts, keys, "right")
    counts = hi - lo
    return np.repeat(lo - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum())), counts


def _gather(rays: Mapping[int, np.ndarray], image: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """``rays[image[e]][kp[e]]`` for every ``e``, ``(E, 2)``: one fancy index per image."""
    out = np.empty((len(image), 2))
    order = np.argsort(image, kind="stable")
    sorted_images = image[order]
    cuts = np.flatnonzero(sorted_images[1:] != sorted_images[:-1]) + 1
    for a, b in zip([0, *cuts.tolist()], [*cuts.tolist(), len(order)], strict=True):
        rows = order[a:b]
        out[rows] = rays[int(sorted_images[a])][kp[rows]]
    return out


@dataclass(frozen=True)
class _Cameras:
    """The estimate's registered cameras as arrays, for every link at once: ``ids`` sorted,
    ``R`` ``(n, 3, 3)``, ``t`` ``(n, 3)``, ``f`` ``(n,)`` in that order."""

    poses: Mapping[int, Pose]
    focal: Mapping[int, float]
    ids: np.ndarray
    R: np.ndarray
    t: np.ndarray
    f: np.ndarray

    @classmethod
    def of(cls, poses: Mapping[int, Pose], focal: Mapping[int, float]) -> _Cameras:
        ids = np.array(sorted(poses), np.int64)
        R = np.array([np.asarray(poses[int(k)][0], np.float64) for k in ids]).reshape(-1, 3, 3)
        t = np.array([np.asarray(poses[int(k)][1], np.float64).reshape(3) for k in ids]).reshape(-1, 3)
        return cls(poses, focal, ids, R, t, np.array([float(focal[int(k)]) for k in ids]))

    def index(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each image's row in the arrays and whether it has one (a pose)."""
        at = np.minimum(np.searchsorted(self.ids, images), max(len(self.ids) - 1, 0))
        return at, (self.ids[at] == images) if len(self.ids) else np.zeros(len(images), bool)


def _centre(pose: Pose) -> np.ndarray:
    R, t = pose
    return -np.asarray(R, np.float64).T @ np.asarray(t, np.float64).reshape(3)


def _world_rays(pose: Pose, x: np.ndarray) -> np.ndarray:
    """Unit world directions ``(n, 3)`` of normalised image points ``x`` ``(n, 2)``."""
    d = np.column_stack([x, np.ones(len(x))]) @ np.asarray(pose[0], np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _midpoints(pose1: Pose, x1: np.ndarray, pose2: Pose, x2: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints ``(n, 3)`` of the closest points of the two cameras' rays through ``x1`` and
    ``x2``, and the depths along each ray (negative: behind the camera; ``nan`` for parallel
    rays)."""
    c1, c2 = _centre(pose1), _centre(pose2)
    d1, d2 = _world_rays(pose1, x1), _world_rays(pose2, x2)
    b = c2 - c1
    dd = np.sum(d1 * d2, axis=1)
    den = 1.0 - dd * dd
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (d1 @ b - dd * (d2 @ b)) / den
        u = (dd * (d1 @ b) - d2 @ b) / den
    X = 0.5 * (c1 + s[:, None] * d1 + c2 + u[:, None] * d2)
    bad = den < 1e-12
    s[bad], u[bad] = np.nan, np.nan
    return X, s, u


def _reprojection(R: np.ndarray, t: np.ndarray, X: np.ndarray, direction: np.ndarray, x: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Normalised reprojection error of ``X`` ``(n, 3)`` against ``x`` (``inf`` behind the
    camera; zeros when ``x`` is None) and the normalised image motion per unit depth of ``X``
    along ``direction``, in the camera ``R`` ``(3, 3)`` or ``(n, 3, 3)``, ``t`` ``(3,)`` or ``(n, 3)``."""
    if R.ndim == 2:
        Y, v = X @ R.T + t, direction @ R.T
    else:
        Y, v = np.einsum("nij,nj->ni", R, X) + t, np.einsum("nij,nj->ni", R, direction)
    z = Y[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = Y[:, :2] / z[:, None]
        motion = (v[:, :2] * z[:, None] - Y[:, :2] * v[:, 2:3]) / (z * z)[:, None]
        err = np.zeros(len(X)) if x is None else np.linalg.norm(proj - x, axis=1)
    err = np.where(z > 0, err, np.inf)
    sens = np.linalg.norm(motion, axis=1)
    return np.nan_to_num(err, nan=np.inf), np.nan_to_num(sens, nan=0.0)
