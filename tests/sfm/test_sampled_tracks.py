"""The global estimate's inputs: the track sample (whole tracks kept or dropped, about the share
asked) and the matches a pair's own rotation is estimated from."""

from __future__ import annotations

import numpy as np

from colmap_miho.sfm.global_estimate import sampled_tracks


def _chain_scene(num_images: int = 6, num_tracks: int = 3000, seed: int = 0):
    """Tracks seen in every image (every pair of images matches every track), plus 20 wrong
    matches per pair that chain keypoints of one image together, as repeated structure does."""
    rng = np.random.default_rng(seed)
    order = {i: rng.permutation(num_tracks + 100) for i in range(1, num_images + 1)}
    matches = {}
    for i in range(1, num_images + 1):
        for j in range(i + 1, num_images + 1):
            m = np.column_stack([order[i][:num_tracks], order[j][:num_tracks]])
            extra = np.column_stack([order[i][num_tracks:num_tracks + 20], order[j][num_tracks + 50:num_tracks + 70]])
            matches[(i, j)] = np.concatenate([m, extra]).astype(np.int64)
    return matches, {i: num_tracks + 100 for i in order}, order


def _track_of(order, i, k):
    return int(np.flatnonzero(order[i] == k)[0])


def test_whole_tracks_are_kept_or_dropped():
    matches, sizes, order = _chain_scene()
    out = sampled_tracks(matches, sizes, per_image=4000, min_pair_matches=15, seed=3)
    kept = {}
    for (i, j), m in out.items():
        for a, b in m:
            ta, tb = _track_of(order, i, a), _track_of(order, j, b)
            assert ta < 3000, "a component with two keypoints of one image is left out"
            assert ta == tb
            kept.setdefault(ta, set()).add((i, j))
    # a kept track keeps its matches in every pair (15 pairs of 6 images)
    assert kept and all(len(pairs) == 15 for pairs in kept.values())


def test_share_follows_the_budget():
    matches, sizes, _ = _chain_scene()
    total = sum(len(m) for m in matches.values())
    per_image = 6000
    out = sampled_tracks(matches, sizes, per_image=per_image, min_pair_matches=15, seed=0)
    ends = 2 * sum(len(m) for m in out.values()) / 6
    assert 0.85 * per_image < ends < 1.15 * per_image
    assert sum(len(m) for m in out.values()) < total


def test_everything_when_under_budget_or_off():
    matches, sizes, _ = _chain_scene(num_tracks=100)
    for per_image in (0, 10**6):
        out = sampled_tracks(matches, sizes, per_image=per_image, min_pair_matches=15, seed=0)
        assert out.keys() == matches.keys()
        assert all(np.array_equal(out[p], matches[p]) for p in matches)


def test_pairs_left_too_small_are_dropped_and_the_draw_is_seeded():
    matches, sizes, _ = _chain_scene()
    matches[(1, 2)] = matches[(1, 2)][-20:]  # 20 matches: too few left after the draw
    a = sampled_tracks(matches, sizes, per_image=2000, min_pair_matches=15, seed=5)
    b = sampled_tracks(matches, sizes, per_image=2000, min_pair_matches=15, seed=5)
    assert a.keys() == b.keys() and all(np.array_equal(a[p], b[p]) for p in a)
    assert all(len(m) >= 15 for m in a.values())
    assert (1, 2) not in a


def test_every_match_when_the_consistent_tracks_are_too_few():
    """Where wrong matches chain nearly every track (a repeated facade in every pair), the
    consistent tracks cannot carry the estimate: the mapper gets every match, as without a
    sample."""
    matches, sizes, order = _chain_scene(num_tracks=600)
    for (i, j), m in matches.items():  # every track also joined to the next one in image j
        shifted = np.column_stack([order[i][:599], order[j][1:600]])
        matches[(i, j)] = np.concatenate([m, shifted]).astype(np.int64)
    out = sampled_tracks(matches, sizes, per_image=500, min_pair_matches=15, seed=0)
    assert out.keys() == matches.keys() and all(np.array_equal(out[p], matches[p]) for p in matches)


def test_evenly_spaced_keeps_the_ends_and_small_pairs():
    from colmap_miho.sfm.global_estimate import evenly_spaced

    m = np.arange(2000, dtype=np.int64).reshape(-1, 2)  # 1000 matches
    out = evenly_spaced({(1, 2): m, (1, 3): m[:10]}, 100)
    assert len(out[(1, 2)]) == 100 and np.array_equal(out[(1, 2)][[0, -1]], m[[0, -1]])
    assert np.array_equal(out[(1, 3)], m[:10])
    assert np.array_equal(evenly_spaced({(1, 2): m}, 0)[(1, 2)], m)


def test_track_labels_times_images_do_not_overflow():
    # 1,000 images of 2,200 keypoints: the matched keypoints of the last images carry labels near
    # 2.2 million, and label * images passes 2**31 (int32 labels wrapped negative at 1,600 images
    # of a calibrated survey); a track that holds two keypoints of one image is still left out
    sizes = {i: 2200 for i in range(1, 1001)}
    rng = np.random.default_rng(0)
    order = {i: rng.permutation(2200) for i in (998, 999, 1000)}
    matches = {}
    for i, j in ((998, 999), (998, 1000), (999, 1000)):
        m = np.column_stack([order[i][:2000], order[j][:2000]])
        extra = np.column_stack([order[i][2000:2020], order[j][2050:2070]])  # chains in one image
        matches[(i, j)] = np.concatenate([m, extra]).astype(np.int64)
    out = sampled_tracks(matches, sizes, per_image=1000, min_pair_matches=15, seed=1)
    assert set(out) == set(matches)
    for (i, j), m in out.items():
        ti = np.argsort(order[i])[m[:, 0]]
        tj = np.argsort(order[j])[m[:, 1]]
        assert np.all(ti == tj) and np.all(ti < 2000)
    kept = len(out[(998, 999)])
    assert 0.18 * 2000 < kept < 0.32 * 2000  # share = 1000 * 3 images / (2 * 6060 matches) = 0.25
