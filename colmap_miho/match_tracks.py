"""Tracks of matches: the connected components of match edges over (image, keypoint) nodes, as
COLMAP's mapper joins them, and the tracks that hold two keypoints of one image.

Nodes number the keypoints of all images, images in id order (:func:`node_offsets`); an edge
is one match between two nodes. Pure numpy/scipy, int64 throughout (node and packed ids pass
2**31 on large surveys).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np


def node_offsets(num_keypoints: Mapping[int, int]) -> tuple[dict[int, int], int]:
    """(image -> its first node, total nodes): the keypoints of the images in id order."""
    offset, total = {}, 0
    for i in sorted(num_keypoints):
        offset[i], total = total, total + int(num_keypoints[i])
    return offset, total


def match_ends(offset: Mapping[int, int], matches: Iterable[tuple[int, int, np.ndarray]]
               ) -> tuple[np.ndarray, np.ndarray]:
    """The (E,) int64 nodes at the two ends of every match of ``(image_a, image_b, (M, 2) keypoint
    indices)``, in the given order."""
    a, b = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for i, j, m in matches:
        m = np.asarray(m, np.int64).reshape(-1, 2)
        a.append(offset[i] + m[:, 0])
        b.append(offset[j] + m[:, 1])
    return np.concatenate(a), np.concatenate(b)


def distinct(values: np.ndarray, size: int | None = None) -> np.ndarray:
    """The sorted distinct entries of the int array ``values`` (``np.unique``'s result): by a mask
    when they lie in ``0..size-1``, else by a sort (numpy's ``unique`` hashes, slower here)."""
    values = np.asarray(values).reshape(-1)
    if size is not None:
        seen = np.zeros(size, dtype=bool)
        seen[values] = True
        return np.flatnonzero(seen).astype(values.dtype, copy=False)
    out = np.sort(values)
    if out.size:
        out = out[np.concatenate([[True], out[1:] != out[:-1]])]
    return out


def components(a: np.ndarray, b: np.ndarray, num_nodes: int) -> tuple[int, np.ndarray]:
    """Connected components of the edges ``a[k] - b[k]`` over ``num_nodes`` nodes: (count, label
    (num_nodes,) int64); labels are numbered by their smallest node, a node without an edge is
    a component of its own."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count, label = connected_components(
        coo_matrix((np.ones(a.size), (a, b)), shape=(num_nodes, num_nodes)), directed=False)
    return int(count), label.astype(np.int64)


def build_tracks(a: np.ndarray, b: np.ndarray, num_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """The tracks of the edges ``a - b``: (nodes (N,) int64 the matched nodes, sorted; track (N,)
    int64 of each, 0..T-1 numbered by their smallest node)."""
    nodes = distinct(np.concatenate([a, b]), num_nodes)
    if not nodes.size:
        return nodes, np.zeros(0, np.int64)
    _, label = components(a, b, num_nodes)
    _, track = np.unique(label[nodes], return_inverse=True)
    return nodes, track.astype(np.int64).reshape(-1)


def image_runs(track: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observations (track (N,), image (N,) non-negative ints) sorted by (track, image), stably:
    (order (N,) int64, start (R,) int64 the position in ``order`` where each run of one track's
    keypoints in one image begins)."""
    track, image = np.asarray(track, np.int64), np.asarray(image, np.int64)
    if not track.size:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    span = int(image.max()) + 1
    if int(track.max()) < np.iinfo(np.int64).max // span:
        order = np.argsort(track * span + image, kind="stable")  # one sort of a packed key
    else:
        order = np.lexsort((image, track))
    t, im = track[order], image[order]
    start = np.ones(t.size, bool)
    start[1:] = (t[1:] != t[:-1]) | (im[1:] != im[:-1])
    return order.astype(np.int64), np.flatnonzero(start)


def repeated_image(track: np.ndarray, image: np.ndarray, num_tracks: int) -> np.ndarray:
    """(num_tracks,) bool: the tracks holding two keypoints of one image (not one scene point:
    a wrong match, or copies of repeated structure chained together)."""
    order, start = image_runs(track, image)
    count = np.diff(np.append(start, order.size))
    out = np.zeros(num_tracks, bool)
    out[np.asarray(track, np.int64)[order[start[count > 1]]]] = True
    return out
