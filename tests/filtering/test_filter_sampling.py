"""Local samples that pass the spread test, iterations counted on valid samples,
MiHo's tolerance (half-match vs full-match thresholds) and the rotation fix's margin."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from planes import make_scene

from colmap_miho import filter_matches
from colmap_miho.filtering.config import FilterConfig
from colmap_miho.filtering.miho import build_problem, choose_rotation
from colmap_miho.filtering.ransac import ransac_round
from colmap_miho.filtering.sampling import LocalCandidates, Sampler, spread_ok
from miho_bench.variants import variant


def _dense_plane(rng, n=400, step=6.0):
    """Matches on a jittered grid ``step`` px apart (closer than t_l = 15 px) under an affine
    map: nearest neighbours are too close for the spread test. (The neighbours are searched
    among the 4k nearest: a grid denser than about 5 px would leave none far enough.)"""
    side = int(np.ceil(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n]
    x1 = 100 + step * g + rng.uniform(-0.5, 0.5, (n, 2))
    A = np.array([[0.9, 0.1], [-0.05, 1.1]])
    return x1, x1 @ A.T + [30.0, -20.0]


@pytest.mark.parametrize("miho", [False, True])
def test_local_samples_pass_the_spread_test(miho):
    rng = np.random.default_rng(0)
    x1, x2 = _dense_plane(rng)
    problem = build_problem(x1, x2, miho=miho)
    cfg = variant(FilterConfig(), local_fraction=1.0)
    pool = np.arange(len(x1))
    sampler = Sampler(problem, pool, cfg)
    sample = sampler.draw(np.random.default_rng(1), 2000)
    ok = spread_ok(problem, sample, cfg.t_l)
    # The 8 nearest matches in (x1, x2) fail the test on this grid; 88% of the drawn samples
    # pass (real SIFT pairs: 93-98%, against 5-21% with the plain nearest neighbours).
    assert ok.mean() > 0.8
    x1x2 = np.c_[x1, x2]
    nearest = sampler._cands._tree.query(x1x2[:50], k=cfg.local_neighbours + 1)[1][:, 1:]
    assert not spread_ok(problem, np.c_[np.arange(50), nearest[:, :3]], cfg.t_l).any()
    # Every local pick is one of its seed's listed neighbours (or, where none was left, the
    # seed itself, which fails the test).
    nb = sampler.neighbours(sample[:, 0])
    listed = (nb[:, :, None] == sample[:, None, 1:]).any(axis=1)
    assert np.all(listed | (sample[:, 1:] == sample[:, :1]))
    assert np.all(listed[ok])


def _brute_neighbours(problem, pool, cfg):
    """Pool neighbours by their definition, from sorted distances (global match indices)."""
    feats = np.c_[problem.x1, problem.x2]
    k, search = cfg.local_neighbours, LocalCandidates.SEARCH * cfg.local_neighbours
    in_pool = np.zeros(len(feats), dtype=bool)
    in_pool[pool] = True
    out = np.full((len(pool), k), -1)
    searched = 0  # rows whose own candidates had too few left
    for row, p in enumerate(pool):
        order = np.argsort(np.linalg.norm(feats - feats[p], axis=1), kind="stable")
        far = np.all(((problem.spread_all[order] - problem.spread_all[p]) ** 2).sum(-1)
                     >= cfg.t_l**2, axis=1)
        listed = order[1:search + 1][(in_pool & far[np.argsort(order)])[order[1:search + 1]]]
        if len(listed) < k:  # too few left among the match's own candidates: the pool's nearest
            searched += 1
            window = order[in_pool[order]][1:search + 1]
            listed = window[far[np.argsort(order)][window]]
        out[row, :min(k, len(listed))] = listed[:k]
    return out, searched


@pytest.mark.parametrize("pool_size", [60, 200, 400])
def test_pool_neighbours_match_their_definition(pool_size, monkeypatch):
    # A grid closer than t_l: most nearest neighbours are too close for the spread test.
    x1, x2 = _dense_plane(np.random.default_rng(5))
    problem = build_problem(x1, x2, miho=True)
    cfg = FilterConfig()
    pool = np.sort(np.random.default_rng(pool_size).choice(len(x1), pool_size, replace=False))
    ref, searched = _brute_neighbours(problem, pool, cfg)
    assert searched > 0.5 * pool_size if pool_size < 400 else searched == 0
    got = []
    for all_at_once in (Sampler.ALL_AT_ONCE, 0):  # every match at the first call, or on demand
        monkeypatch.setattr(Sampler, "ALL_AT_ONCE", all_at_once)
        sampler = Sampler(problem, pool, cfg, LocalCandidates(problem, cfg))
        pos = np.random.default_rng(0).permutation(pool_size)
        nb = np.concatenate([sampler.neighbours(part) for part in np.array_split(pos, 3)])
        nb = nb[np.argsort(pos)]
        got.append(np.where(nb >= 0, pool[np.maximum(nb, 0)], -1))
    np.testing.assert_array_equal(got[0], ref)
    np.testing.assert_array_equal(got[1], ref)


def test_iterations_count_spread_out_samples():
    rng = np.random.default_rng(3)
    x1, x2 = _dense_plane(rng, n=300)
    noise = rng.uniform(0, 600, (300, 2))  # a second set of random matches
    x1, x2 = np.r_[x1, noise], np.r_[x2, rng.uniform(0, 600, (300, 2))]
    problem = build_problem(x1, x2, miho=False)
    cfg = variant(FilterConfig(method="mop", max_iters=300), min_iters=300)
    res, _ = ransac_round(problem, np.arange(len(x1)), cfg, np.random.default_rng(0), [])
    st = res.stats
    assert st["samples"] >= cfg.min_iters  # c_min counts samples that pass the spread test
    assert st["drawn"] >= st["samples"] >= st["valid"]
    assert res.count >= 280  # the plane is found



def test_iteration_cap_follows_the_method_unless_given():
    assert FilterConfig(method="mop_miho", max_iters=None).iteration_cap == 500
    assert FilterConfig(method="mop_miho_star", max_iters=None).iteration_cap == 500
    assert FilterConfig(method="mop", max_iters=None).iteration_cap == 2000
    assert FilterConfig(method="mop_miho", max_iters=700).iteration_cap == 700
    with pytest.raises(ValueError, match="min_iters"):
        FilterConfig(method="mop_miho", max_iters=10)  # below c_min
    with pytest.raises(ValueError, match="batch_growth"):
        FilterConfig(batch_growth=0.5)


def test_batch_growth_bounds_each_batch(monkeypatch):
    # One plane among twice as many random matches, uniform sampling: the first batch's best
    # model is weak, so without a growth limit the next batch is sized by its far bound.
    rng = np.random.default_rng(3)
    x1, x2 = _dense_plane(rng, n=300)
    x1, x2 = np.r_[x1, rng.uniform(0, 600, (600, 2))], np.r_[x2, rng.uniform(0, 600, (600, 2))]
    problem = build_problem(x1, x2, miho=False)
    sizes: list[int] = []
    draw = Sampler.draw

    def recorded(self, rng, size):
        sizes.append(size)
        return draw(self, rng, size)

    monkeypatch.setattr(Sampler, "draw", recorded)
    runs = {}
    for growth in (0.0, 2.0):
        sizes.clear()
        cfg = variant(FilterConfig(method="mop", batch_growth=growth), sampling="uniform", batch_size=32)
        res, _ = ransac_round(problem, np.arange(len(x1)), cfg, np.random.default_rng(1), [])
        assert res is not None and res.count >= 290  # the plane is found either way
        runs[growth] = list(sizes)
    assert all(s <= 8 * 32 for s in runs[0.0] + runs[2.0])
    assert max(b / a for a, b in pairwise(runs[0.0])) > 2  # the limit can bite
    assert all(b <= 2 * a for a, b in pairwise(runs[2.0]))
    assert sum(runs[2.0]) < sum(runs[0.0])


def _plane_with_offsets(offsets):
    """300 exact matches of one homography plus one match per offset, its image-2 point moved
    by ``offset`` px along x (the full match is ``offset`` px off)."""
    rng = np.random.default_rng(5)
    H = np.array([[1.05, 0.08, 40.0], [-0.03, 0.97, 15.0], [2e-5, 1e-5, 1.0]])
    x1 = rng.uniform(50, 750, (300 + len(offsets), 2))
    y = np.c_[x1, np.ones(len(x1))] @ H.T
    x2 = y[:, :2] / y[:, 2:]
    x2[300:, 0] += offsets
    return x1, x2


def test_miho_threshold_half_vs_full():
    offsets = [5.0, 10.0, 20.0, 26.0, 40.0]
    x1, x2 = _plane_with_offsets(offsets)
    half = filter_matches(x1, x2, config=FilterConfig(method="mop_miho", miho_threshold="half"))
    full = filter_matches(x1, x2, config=FilterConfig(method="mop_miho", miho_threshold="full"))
    search = filter_matches(x1, x2, method="mop_miho")  # default "full_search"
    mop = filter_matches(x1, x2, method="mop")
    assert half.inliers[:300].all() and full.inliers[:300].all()
    assert FilterConfig().miho_threshold == "full_search"
    # Half-match thresholds: each half is about offset / 2 off, so up to ~2 t_l passes.
    assert half.inliers[300:].tolist() == [True, True, True, True, False]
    # Full-match thresholds: the same tolerance as MOP's.
    assert full.inliers[300:].tolist() == [True, True, False, False, False]
    assert mop.inliers[300:].tolist() == full.inliers[300:].tolist()
    # Default: planes searched with the full-match tolerance, matches kept with half-matches.
    assert search.inliers[300:].tolist() == half.inliers[300:].tolist()
    with pytest.raises(ValueError, match="miho_threshold"):
        FilterConfig(miho_threshold="both")


def test_rotation_fix_keeps_upright_pairs_among_outliers():
    # 5% correct upright matches among random ones: outlier pairs decide the raw counts, so
    # only a clear margin may turn image 2 (measured: without it, 2 of these 8 seeds mirrored).
    for seed in range(8):
        sc = make_scene(np.random.default_rng(seed), n_planes=1, per_plane=60, outlier_ratio=0.95)
        _, idx, _ = choose_rotation(sc.x1, sc.x2, np.random.default_rng(seed), reflections=True)
        assert idx == 0, seed
