"""The tracks of matches (:mod:`colmap_miho.match_tracks`): components over (image, keypoint)
nodes, their numbering, and the tracks that hold two keypoints of one image."""

from __future__ import annotations

import numpy as np

from colmap_miho.match_tracks import (
    build_tracks,
    components,
    image_runs,
    match_ends,
    node_offsets,
    repeated_image,
)


def test_offsets_ends_and_tracks_of_a_small_graph():
    # images 7 (3 keypoints), 2 (2), 5 (4): nodes in id order 2, 5, 7
    offset, total = node_offsets({7: 3, 2: 2, 5: 4})
    assert offset == {2: 0, 5: 2, 7: 6} and total == 9
    a, b = match_ends(offset, [(2, 5, np.array([[0, 1], [1, 3]])), (5, 7, [[1, 2]]), (2, 7, np.zeros((0, 2)))])
    assert a.dtype == np.int64 and a.tolist() == [0, 1, 3] and b.tolist() == [3, 5, 8]
    count, label = components(a, b, total)
    assert label.dtype == np.int64 and count == 9 - 3  # three edges, no cycle
    nodes, track = build_tracks(a, b, total)
    assert nodes.tolist() == [0, 1, 3, 5, 8]
    assert track.tolist() == [0, 1, 0, 1, 0]  # numbered by their smallest node
    empty = build_tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), 4)
    assert empty[0].size == 0 and empty[1].size == 0


def test_repeated_image_and_the_runs():
    track = np.array([2, 0, 0, 1, 2, 0, 1])
    image = np.array([4, 1, 3, 1, 4, 1, 2])
    order, start = image_runs(track, image)
    assert np.array_equal(order, np.lexsort((image, track)))
    # runs: (0, 1) x2, (0, 3), (1, 1), (1, 2), (2, 4) x2
    assert start.tolist() == [0, 2, 3, 4, 5]
    assert repeated_image(track, image, 4).tolist() == [True, False, True, False]


def test_runs_of_huge_track_and_image_ids_sort_without_overflow():
    track = np.array([2**62, 3, 2**62, 3], np.int64)
    image = np.array([5, 2**40, 5, 1], np.int64)
    order, start = image_runs(track, image)
    assert np.array_equal(order, np.lexsort((image, track)))
    assert start.tolist() == [0, 1, 2]


def test_random_graphs_agree_with_a_plain_union_find():
    rng = np.random.default_rng(0)
    n = 300
    a, b = rng.integers(0, n, 200), rng.integers(0, n, 200)
    parent = list(range(n))

    def root(k: int) -> int:
        while parent[k] != k:
            k = parent[k]
        return k

    for x, y in zip(a.tolist(), b.tolist(), strict=True):
        parent[root(x)] = root(y)
    count, label = components(a, b, n)
    roots = np.array([root(k) for k in range(n)])
    assert count == len(set(roots.tolist()))
    for k in range(n):  # same component <=> same label
        assert np.array_equal(label == label[k], roots == roots[k])
    first = [int(np.flatnonzero(label == c)[0]) for c in range(count)]
    assert first == sorted(first)  # labels numbered by their smallest node
