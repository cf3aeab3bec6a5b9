"""Groups of whole tracks (``TrackPlan.groups``): compact, bounded in images, deterministic, and
walked one by one they move every keypoint exactly as the walk of the whole plan does."""

from __future__ import annotations

import pickle
from collections.abc import Mapping
from types import SimpleNamespace

import numpy as np
import pytest

from colmap_miho.refinement.config import NCCConfig, TrackConfig
from colmap_miho.refinement.pairwise import RefineResult
from colmap_miho.refinement.rectify.local_affine import local_affine_pairs
from colmap_miho.refinement.tracks.build import build_track_plan
from colmap_miho.refinement.tracks.walk import walk_tracks

LOCAL = (6, 2.0)


def random_scene(seed: int, n_images: int = 9, n_tracks: int = 400):
    """Tracks over sequential windows of images (as a video or a walk around an object),
    a few long ones, duplicates and conflicts, two filter clusters per pair, and some
    unrefined matches. Returns (keypoints, pair_matches, results, unrefined)."""
    rng = np.random.default_rng(seed)
    kps: dict[int, list] = {i: [] for i in range(1, n_images + 1)}
    pm: dict[tuple, list] = {}
    for t in range(n_tracks):
        length = int(rng.integers(2, 5)) if t % 40 else n_images
        start = int(rng.integers(1, n_images - length + 2))
        members = list(range(start, start + length))
        centre = rng.uniform(20, 480, 2)
        obs = []
        for i in members:
            obs.append((i, len(kps[i])))
            kps[i].append(centre + rng.normal(0, 3, 2))
        if t % 50 == 7:  # a second keypoint of one image: a conflict (far) or a duplicate
            i = members[0]
            obs.append((i, len(kps[i])))
            kps[i].append(kps[i][-1] + (30.0 if t % 100 == 7 else 0.4))
        for a in range(len(obs)):
            for b in range(a + 1, len(obs)):
                (i, ki), (j, kj) = obs[a], obs[b]
                if i != j and rng.random() < 0.8:
                    key, row = ((i, j), [ki, kj]) if i < j else ((j, i), [kj, ki])
                    pm.setdefault(key, []).append(row)
    keypoints = {i: np.asarray(v, np.float64).reshape(-1, 2) for i, v in kps.items()}
    matches = {k: np.asarray(v, np.int64) for k, v in pm.items()}
    unrefined = {}
    for k in list(matches)[::7]:  # some pairs never filtered
        unrefined[k] = matches.pop(k)
    results = {}
    for k, m in matches.items():
        labels = rng.integers(-1, 2, len(m))  # -1: kept, no homography
        homs = np.tile(np.eye(3), (2, 2, 1, 1))
        homs[1, 1, :2, 2] = rng.normal(0, 0.5, 2)
        results[k] = SimpleNamespace(inliers=rng.random(len(m)) < 0.95, labels=labels,
                                     patch_homographies=homs)
    return keypoints, matches, results, unrefined


class PullRefiner:
    """Moves each free keypoint a quarter of the way towards its fixed partner plus a term of
    the homography pair it got; its NCC depends on the positions, so partner choice and order
    matter. Records the homography pair each (moving image, keypoint) was refined with."""

    def __init__(self):
        self.homs = {}

    def __call__(self, image1, image2, pts1, pts2, homs, *, move, config, **kw):
        p1, p2 = np.array(pts1, float), np.array(pts2, float)
        h = np.asarray(homs)
        new = p2 + 0.25 * (p1 - p2) + 0.01 * h.reshape(len(p2), -1)[:, :2].sum(1, keepdims=True)
        ncc = np.cos(p1[:, 0] * 0.37 + p2[:, 1] * 0.11)
        for row, pt in enumerate(p2):
            self.homs[(image2, float(pt[0]), float(pt[1]))] = h[row].copy()
        n = len(p1)
        return RefineResult(pts1=p1, pts2=new, ncc_before=np.zeros(n), ncc_after=ncc,
                            moved_side=np.full(n, 2, np.int8), displacement=np.linalg.norm(new - p2, axis=1),
                            rejected=np.zeros(n, bool), stats={})


def _images(kps):
    return {i: i for i in kps}  # the fake reads no pixels: the "image" is its id


def _merge(kps, plan, walks):
    out = {i: k.copy() for i, k in kps.items()}
    against = {i: np.full((len(k), 2), -1, np.int64) for i, k in kps.items()}
    for r in walks:
        for i in r.keypoints:
            ch = np.any(r.keypoints[i] != kps[i], 1)
            out[i][ch] = r.keypoints[i][ch]
            got = r.refined_against[i][:, 0] >= 0
            assert not (against[i][got, 0] >= 0).any()  # no keypoint in two groups
            against[i][got] = r.refined_against[i][got]
    return out, against


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("max_images", [1, 2, 3, 5, 100])
def test_groups_walk_exactly_like_the_whole_plan(seed, max_images):
    kps, pm, res, unref = random_scene(seed)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref, local_affine=LOCAL)
    ncc = NCCConfig.pairwise(rectify={"mode": "both"})
    whole_fake = PullRefiner()
    whole = walk_tracks(_images(kps), plan, ncc_config=ncc, refine_fn=whole_fake)
    groups = plan.groups(max_images)
    assert groups == [] or len(groups) >= 1
    fake = PullRefiner()
    walks = [walk_tracks(_images(kps), plan.attach_local(g), ncc_config=ncc, refine_fn=fake)
             for g in groups]
    merged, against = _merge(kps, plan, walks)
    assert whole.stats["moved"] > 200
    for i in kps:
        np.testing.assert_array_equal(merged[i], whole.keypoints[i])
        np.testing.assert_array_equal(against[i], whole.refined_against[i])
    assert whole_fake.homs.keys() == fake.homs.keys()
    for key, h in whole_fake.homs.items():
        np.testing.assert_array_equal(fake.homs[key], h)
    assert sum(w.stats["refined"] for w in walks) == whole.stats["refined"]
    assert sum(g.to_refine for g in groups) == plan.to_refine


@pytest.mark.parametrize("max_images", [2, 3, 4, 9])
def test_groups_are_bounded_compact_and_deterministic(max_images):
    kps, pm, res, unref = random_scene(3)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref, local_affine=LOCAL)
    groups = plan.groups(max_images)
    again = plan.groups(max_images)
    assert len(groups) == len(again)
    for a, b in zip(groups, again, strict=True):
        assert pickle.dumps(a) == pickle.dumps(b)
    seen: set = set()
    for g in groups:
        images = set(np.unique(g.node_image).tolist())
        assert set(g.keypoints) == images
        # bounded, unless one track has more images: then by its image count
        biggest = max(len(set(g.node_image[g.track == t].tolist())) for t in range(g.anchors.size))
        assert len(images) <= max(max_images, biggest)
        # compact: only its own nodes, every node has an edge, every pair is used
        assert np.array_equal(np.unique(np.concatenate([g.edge_a, g.edge_b])), np.arange(g.num_nodes))
        assert np.array_equal(np.unique(g.edge_pair), np.arange(len(g.pairs)))
        assert g.refinable().all() and g.local_homs is None
        nodes = set(zip(g.node_image.tolist(), g.node_kp.tolist(), strict=True))
        assert not nodes & seen
        seen |= nodes
    # pickled, a group costs its own size: the keypoint arrays of its images, 8 bytes per
    # node and edge array entry, its pairs' filter homographies and a fixed overhead (never the whole plan)
    whole = len(pickle.dumps(plan))
    for g in groups:
        own = sum(k.nbytes for k in g.keypoints.values()) + 8 * (4 * g.num_nodes + 6 * g.edge_a.size)
        assert len(pickle.dumps(g)) <= own + 4096 + 600 * len(g.pairs)
        if len(groups) > 3:
            assert len(pickle.dumps(g)) < 0.5 * whole
    # consecutive groups share images (the schedule): most of them
    shared = [bool(set(a.keypoints) & set(b.keypoints)) for a, b in zip(groups, groups[1:], strict=False)]
    assert not shared or np.mean(shared) >= 0.8
    with pytest.raises(ValueError, match="max_images"):
        plan.groups(0)


def test_local_pairs_are_those_of_the_whole_pair():
    """Lazy local affine pairs, per group, are bit-identical to fitting every pair over all of
    its edges up front (what the plan did before) on the edges the walk can use; and a
    group must get them attached."""
    kps, pm, res, unref = random_scene(5, n_tracks=900)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref, local_affine=LOCAL)
    starts = np.searchsorted(plan.edge_pair, np.arange(len(plan.pairs) + 1))
    eager = []
    for p, (id1, id2) in enumerate(plan.pairs):
        sl = slice(starts[p], starts[p + 1])
        eager.append(local_affine_pairs(kps[id1][plan.node_kp[plan.edge_a[sl]]],
                                        kps[id2][plan.node_kp[plan.edge_b[sl]]],
                                        plan.edge_label[sl], plan.pair_homs[p], k=LOCAL[0],
                                        max_residual_px=LOCAL[1]))
    fitted = skipped = 0
    for g in plan.groups(3):
        with pytest.raises(ValueError, match="attach"):
            g.local_pairs(0)
        full = plan.attach_local(g)
        gs = np.searchsorted(full.edge_pair, np.arange(len(full.pairs) + 1))
        for q, p in enumerate(full.source_pairs):
            rows = full.source_rows[gs[q]:gs[q + 1]]
            # the edges the walk can refine along; the others keep the filter's pair
            step = plan.walk_steps()[starts[p] + rows]
            np.testing.assert_array_equal(full.local_pairs(q)[step], eager[p][rows][step])
            label = plan.edge_label[starts[p] + rows][~step]
            np.testing.assert_array_equal(full.local_pairs(q)[~step],
                                          plan.pair_homs[p][label])
            skipped += int((~step).sum())
            fitted += int((eager[p][rows][:, 0] != np.eye(3)).any(axis=(1, 2)).sum() == 0)
        plan.release_local(full.source_pairs)
    assert not plan._local_cache
    assert fitted > 0 and skipped > 0


def test_groups_fit_their_own_local_pairs_with_the_same_bits():
    """A group given its local inputs (as a worker gets it, pickled) fits the same local
    affine pairs as the plan attaches, bit for bit, from the edges of its own clusters only."""
    kps, pm, res, unref = random_scene(6, n_tracks=900)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref, local_affine=LOCAL)
    moved = 0
    for g in plan.groups(3):
        own = pickle.loads(pickle.dumps(plan.with_local_inputs(g)))
        attached = plan.attach_local(g)
        assert own.local_homs is None and len(own.local_inputs) == len(own.pairs)
        for q in range(len(own.pairs)):
            x1, _, labels, at, fit = own.local_inputs[q]
            assert at.size == fit.size == int((own.edge_pair == q).sum())
            own_labels = own.edge_label[own.edge_pair == q]
            np.testing.assert_array_equal(np.unique(labels), np.unique(own_labels))
            np.testing.assert_array_equal(own.local_pairs(q), attached.local_pairs(q))
            fitted = own.local_pairs(q) != own.pair_homs[q][own_labels]
            moved += int(fitted.any(axis=(1, 2, 3)).sum())
        plan.release_local(attached.source_pairs)
    assert moved > 0
    nolocal = build_track_plan(kps, pm, res, unrefined_matches=unref)
    g = nolocal.groups(3)[0]
    assert nolocal.with_local_inputs(g) is g and g.local_pairs(0) is None
    with pytest.raises(ValueError, match="groups"):
        plan.with_local_inputs(plan)


def test_groups_of_a_group_and_no_walked_track():
    kps = {1: np.zeros((1, 2)), 2: np.zeros((1, 2))}
    pm = {(1, 2): np.array([[0, 0]])}
    res = {(1, 2): SimpleNamespace(labels=np.array([-1]), patch_homographies=np.zeros((0, 2, 3, 3)))}
    plan = build_track_plan(kps, pm, res)
    assert plan.groups(4) == []
    kps, pm, res, unref = random_scene(2)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref)
    g = max(plan.groups(4), key=lambda g: g.anchors.size)
    parts = g.groups(4, max_edges=1)  # one walked unit each
    assert len(parts) == g.anchors.size > 1
    assert sum(p.to_refine for p in parts) == g.to_refine
    whole = walk_tracks(_images(g.keypoints), g, refine_fn=PullRefiner())
    merged, _ = _merge(g.keypoints, g, [walk_tracks(_images(p.keypoints), p, refine_fn=PullRefiner())
                                         for p in parts])
    for i in g.keypoints:
        np.testing.assert_array_equal(merged[i], whole.keypoints[i])


def test_groups_on_real_images_move_keypoints_like_the_whole_walk(shared_data):
    """Real NCC (local affine pairs on, as shipped) on 5 Middlebury temple images: the walk of
    the groups for several image bounds refines the same keypoints against the same partners
    as the whole walk, to the same positions bit for bit (the NCC of a match does not depend on
    the other matches of its refine call)."""
    import cv2

    from miho_bench.frontend import filtered_multiview_matches

    folder = shared_data / "middlebury_temple_sparse_ring" / "images"
    files = sorted(folder.iterdir())[:5]
    images = {i + 1: cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for i, f in enumerate(files)}
    kps, matches, results = filtered_multiview_matches(images, max_features=600)
    assert len(matches) >= 4
    ncc = NCCConfig.pairwise(device="cpu", template_radius=6)
    plan = build_track_plan(kps, matches, results, local_affine=(ncc.rectify.neighbours,
                                                                 ncc.rectify.max_residual_px))
    whole = walk_tracks(images, plan, ncc_config=ncc, track_config=TrackConfig())
    assert whole.stats["moved"] > 50
    for max_images, max_edges in ((2, 100), (3, 400), (5, 250)):
        groups = plan.groups(max_images, max_edges)
        assert len(groups) > 1
        walks = [walk_tracks(images, plan.attach_local(g), ncc_config=ncc) for g in groups]
        merged, against = _merge(kps, plan, walks)
        assert sum(w.stats["moved"] for w in walks) == whole.stats["moved"]
        for i in kps:
            np.testing.assert_array_equal(against[i], whole.refined_against[i])
            np.testing.assert_array_equal(merged[i] != kps[i], whole.keypoints[i] != kps[i])
            np.testing.assert_array_equal(merged[i], whole.keypoints[i])


def test_groups_bounded_in_edges_cover_the_plan():
    kps, pm, res, unref = random_scene(4)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref)
    by_images = plan.groups(9)
    groups = plan.groups(9, max_edges=40)
    assert len(groups) > len(by_images)
    for g in groups:
        assert g.edge_a.size <= 40 or g.anchors.size == 1
    assert sum(g.to_refine for g in groups) == plan.to_refine
    assert sum(g.edge_a.size for g in groups) == sum(g.edge_a.size for g in by_images)
    with pytest.raises(ValueError, match="max_edges"):
        plan.groups(9, max_edges=0)


class CountingImages(Mapping):
    """Images by id through an LRU cache of ``size``; ``decodes`` counts the misses."""

    def __init__(self, ids, size):
        self.ids, self.size, self.cache, self.decodes = list(ids), size, [], 0

    def __getitem__(self, i):
        if i in self.cache:
            self.cache.remove(i)
        else:
            self.decodes += 1
            if len(self.cache) >= self.size:
                self.cache.pop(0)
        self.cache.append(i)
        return i

    def __iter__(self):
        return iter(self.ids)

    def __len__(self):
        return len(self.ids)


def test_snake_order_of_a_level_decodes_fewer_images(monkeypatch):
    """The calls of a level in snake order: a permutation, reversed every other level, far
    fewer decodes than the plain pair order through a small LRU cache; a walk in either order
    moves the keypoints identically."""
    from colmap_miho.refinement.tracks import walk

    n = 8
    pairs = [(i, j) for i in range(1, n + 1) for j in range(i + 1, n + 1)]
    groups = [SimpleNamespace(pair=p, side=2) for p in pairs]
    order = [g.pair for g in walk.cache_order(groups, 0)]
    assert sorted(order) == pairs and order[:3] == [(1, 2), (1, 3), (1, 4)]
    assert order[n - 1:n + 1] == [(2, 8), (2, 7)]  # the second row runs backwards
    assert [g.pair for g in walk.cache_order(groups, 1)] == order[::-1]
    snake_cost, plain_cost = CountingImages(range(1, n + 1), 4), CountingImages(range(1, n + 1), 4)
    for a, b in order:
        snake_cost[a], snake_cost[b]
    for a, b in pairs:
        plain_cost[a], plain_cost[b]
    assert snake_cost.decodes <= 0.7 * plain_cost.decodes  # measured 20 vs 29

    kps, pm, res, unref = random_scene(6)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref)
    snake_images = CountingImages(kps, 3)
    snake = walk_tracks(snake_images, plan, refine_fn=PullRefiner())
    monkeypatch.setattr(walk, "cache_order", lambda groups, level: groups)
    plain_images = CountingImages(kps, 3)
    plain = walk_tracks(plain_images, plan, refine_fn=PullRefiner())
    for i in kps:
        np.testing.assert_array_equal(snake.keypoints[i], plain.keypoints[i])
        np.testing.assert_array_equal(snake.refined_against[i], plain.refined_against[i])
    assert snake_images.decodes < plain_images.decodes


@pytest.mark.parametrize("seed", [0, 4])
def test_walk_refines_along_walk_steps_only(seed):
    """Every keypoint the walk refines is refined against a partner joined to it by one of
    :meth:`~colmap_miho.refinement.tracks.plan.TrackPlan.walk_steps` (so the local pairs of the other
    edges are never read), and the walk does use edges of every level."""
    kps, pm, res, unref = random_scene(seed)
    plan = build_track_plan(kps, pm, res, unrefined_matches=unref, local_affine=LOCAL)
    steps = plan.walk_steps()
    assert 0 < steps.sum() < plan.refinable().sum()
    assert not (steps & ~plan.refinable()).any()
    node = {(int(i), int(k)): n for n, (i, k) in enumerate(zip(plan.node_image, plan.node_kp,
                                                                strict=True))}
    allowed = {frozenset((int(a), int(b))) for a, b in zip(plan.edge_a[steps],
                                                           plan.edge_b[steps], strict=True)}
    walk = walk_tracks(_images(kps), plan, ncc_config=NCCConfig.pairwise(rectify={"mode": "both"}),
                       refine_fn=PullRefiner())
    used = 0
    for i, against in walk.refined_against.items():
        for k in np.flatnonzero(against[:, 0] >= 0):
            partner = node[(int(against[k, 0]), int(against[k, 1]))]
            assert frozenset((node[(int(i), int(k))], partner)) in allowed
            used += 1
    assert used == walk.stats["refined"] > 200


def test_distinct_is_numpys_unique():
    from colmap_miho.match_tracks import distinct

    rng = np.random.default_rng(0)
    for n in (0, 1, 7, 5000):
        v = rng.integers(0, 300, n)
        np.testing.assert_array_equal(distinct(v, 300), np.unique(v))
        np.testing.assert_array_equal(distinct(v * 1_000_003 - 17), np.unique(v * 1_000_003 - 17))
        assert distinct(v, 300).dtype == np.unique(v).dtype


def _reference_group_of(plan, max_images: int, max_edges: int | None) -> np.ndarray:
    """The group of each walked unit by the rule of ``TrackPlan.groups`` written as the plain
    sweep over units (one set union per unit)."""
    unit, anchors = plan.walked_units()
    e_ids = np.flatnonzero(unit >= 0)
    eu = unit[e_ids]
    images = [set() for _ in range(anchors.size)]
    for u, a, b in zip(eu, plan.node_image[plan.edge_a[e_ids]], plan.node_image[plan.edge_b[e_ids]],
                       strict=True):
        images[u] |= {int(a), int(b)}
    tuples = [tuple(sorted(s)) for s in images]
    order = sorted(range(anchors.size), key=lambda u: (tuples[u], u))
    n_edges = np.bincount(eu, minlength=anchors.size)
    limit = max_edges or eu.size
    group_of = np.empty(anchors.size, np.int64)
    g, current, edges, cap = -1, set(), 0, max_images
    for u in order:
        both = current | images[u]
        edges += n_edges[u]
        if g < 0 or len(both) > max(cap, len(images[u])) or edges > limit:
            g, both, edges, cap = g + 1, set(images[u]), n_edges[u], max_images
        group_of[u] = g
        current, cap = both, max(cap, len(images[u]))
    return group_of


@pytest.mark.parametrize("table", [True, False])
def test_groups_follow_the_sweep_over_units(monkeypatch, table):
    """The groups are exactly those of the plain sweep over units (runs of units with the same
    images swept at once; the units sorted with numpy's padded table or in Python), for
    bounds in images, in edges (units larger than the bound alone), and both."""
    from colmap_miho.refinement.tracks import plan as plan_module

    if not table:
        monkeypatch.setattr(plan_module, "MAX_TUPLE_TABLE", 0)
    for seed in (1, 5):
        kps, pm, res, unref = random_scene(seed, n_images=12, n_tracks=600)
        plan = build_track_plan(kps, pm, res, unrefined_matches=unref)
        unit, anchors = plan.walked_units()
        n_edges = np.bincount(unit[unit >= 0], minlength=anchors.size)
        assert n_edges.max() > 12  # the long tracks exceed the smallest edge bound below
        for max_images, max_edges in ((12, None), (3, None), (5, 40), (12, 12), (2, 7)):
            groups = plan.groups(max_images, max_edges)
            expected = _reference_group_of(plan, max_images, max_edges)
            assert len(groups) == expected.max() + 1
            for g, grp in enumerate(groups):
                mine = np.flatnonzero(expected == g)
                # the group's anchors, as (image, keypoint), are those of its units
                got = sorted(zip(grp.node_image[grp.anchors].tolist(),
                                 grp.node_kp[grp.anchors].tolist(), strict=True))
                ref = sorted(zip(plan.node_image[anchors[mine]].tolist(),
                                 plan.node_kp[anchors[mine]].tolist(), strict=True))
                assert got == ref
