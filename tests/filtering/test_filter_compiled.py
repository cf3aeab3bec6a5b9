"""The compiled (numba) batch kernels against their numpy reference.

The spread test, the local draws, the inlier masks and the errors are the same decisions /
bits for the same inputs; the minimal solver sums in a fixed order where numpy's matmul may
not, so its homographies agree to ``H_ATOL`` (unit-norm matrices) and the one-way float32
bound to within one inlier on at most ``BOUND_OFF`` of the hypotheses.
"""

from __future__ import annotations

import numpy as np
import pytest
from planes import make_scene

from colmap_miho import filter_matches
from colmap_miho.filtering import compiled as filter_compiled
from colmap_miho.filtering.compiled import ransac, sampling
from colmap_miho.filtering.config import FilterConfig
from colmap_miho.filtering.miho import build_problem, choose_rotation
from colmap_miho.filtering.ransac import _refit
from colmap_miho.filtering.sampling import LocalCandidates, Sampler, checked_samples, spread_ok
from colmap_miho.filtering.scoring import NumpyScoring, hypotheses_from_samples
from miho_bench.variants import variant

H_ATOL = 1e-12  # entries of unit-Frobenius-norm homographies
REFIT_ATOL = 1e-9  # the same, least-squares refits (an eigenvector of A^T A: less well set)
BOUND_OFF = 0.01  # share of hypotheses whose one-way bound may differ (by one inlier)
SAME_FLAGS = 0.999  # share of matches with the same inlier flag, whole filter


def _problem(miho: bool, seed: int = 3):
    rng = np.random.default_rng(seed)
    sc = make_scene(rng, n_planes=3, per_plane=120, outlier_ratio=0.5)
    return sc, build_problem(sc.x1, sc.x2, miho=miho, full_match=miho), rng


def _samples(sc, rng, n=768):
    """Random minimal samples, a third of them within one plane (valid hypotheses)."""
    plane0 = np.flatnonzero(sc.plane == 0)
    return np.concatenate([rng.integers(0, len(sc.x1), (2 * n // 3, 4)),
                           plane0[rng.integers(0, len(plane0), (n // 3, 4))]])


@pytest.mark.parametrize("miho", [False, True])
def test_spread_test_is_the_same(miho):
    sc, problem, rng = _problem(miho)
    sample = _samples(sc, rng, 3000)
    for t_l in (5.0, 15.0, 40.0):
        want = spread_ok(problem, sample, t_l)
        assert 0 < want.sum() < len(want)
        got = NumpyScoring(compiled=True).spread_ok(problem, sample, t_l)
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("method", ["mop", "mop_star", "mop_miho", "mop_miho_star"])
def test_hypotheses_and_bounds_match_numpy(method):
    cfg = FilterConfig(method=method)
    sc, problem, rng = _problem(cfg.is_miho)
    sample = _samples(sc, rng)
    ok = spread_ok(problem, sample, cfg.t_l)
    pool = np.sort(rng.choice(len(sc.x1), 2 * len(sc.x1) // 3, replace=False))
    t2 = cfg.t_l**2
    ref = NumpyScoring(compiled=False)
    want, want_ub = ref.hypotheses(problem, sample, cfg, ok, pool, t2)
    got, got_ub = NumpyScoring(compiled=True).hypotheses(problem, sample, cfg, ok, pool, t2)
    assert len(want) > 200 and len(got) == len(want)
    if cfg.reflection_check:  # the check rejects some samples that pass the rest
        assert len(checked_samples(problem, sample, cfg, ok)) < ok.sum()
    np.testing.assert_array_equal(got.sample, want.sample)
    np.testing.assert_array_equal(got.sign, want.sign)
    np.testing.assert_array_equal(got.sign_inv, want.sign_inv)
    np.testing.assert_allclose(got.H, want.H, rtol=0, atol=H_ATOL)
    np.testing.assert_allclose(got.Hinv, want.Hinv, rtol=0, atol=H_ATOL)
    assert want_ub.max() > 50  # some hypotheses hit a plane: the bounds are informative
    off = np.abs(got_ub - want_ub)
    assert off.max() <= 1 and np.mean(off > 0) <= BOUND_OFF


@pytest.mark.parametrize("miho", [False, True])
def test_masks_and_errors_are_the_same_bits(miho):
    cfg = FilterConfig(method="mop_miho" if miho else "mop")
    sc, problem, rng = _problem(miho)
    sample = _samples(sc, rng)
    hyp = hypotheses_from_samples(problem, sample, cfg, spread_ok(problem, sample, cfg.t_l))
    pool = np.sort(rng.choice(len(sc.x1), 2 * len(sc.x1) // 3, replace=False))
    ref, fast = NumpyScoring(compiled=False), NumpyScoring(compiled=True)
    err = ref.error_sq(problem, hyp, pool)
    assert np.isinf(err).any() and (err <= cfg.t_l**2).any()
    np.testing.assert_array_equal(fast.error_sq(problem, hyp, pool), err)
    for t2 in (cfg.t_l**2, cfg.strict_threshold**2):
        np.testing.assert_array_equal(fast.masks(problem, hyp, pool, t2)[0],
                                      ref.masks(problem, hyp, pool, t2)[0])


@pytest.mark.parametrize("miho", [False, True])
def test_local_draws_are_the_same(miho):
    sc, problem, rng = _problem(miho)
    cfg = variant(FilterConfig(), local_fraction=1.0)
    pool = np.sort(rng.choice(len(sc.x1), 300, replace=False))
    ref = Sampler(problem, pool, cfg).draw(np.random.default_rng(7), 1000)
    got = Sampler(problem, pool, cfg, compiled=True).draw(np.random.default_rng(7), 1000)
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("small", [False, True])
def test_batches_of_draws_over_the_rounds_are_the_same(small):
    """Several batches per pool, over shrinking pools sharing the problem's candidates (as
    the rounds draw them), the compiled sampler against the numpy one: the same samples
    and the same generator state after each batch; on a problem of at most
    Sampler.ALL_AT_ONCE matches too (no candidates: the pool searched whole)."""
    rng = np.random.default_rng(6)
    sc = (make_scene(rng, n_planes=2, per_plane=80, outlier_ratio=0.3) if small
          else make_scene(rng, n_planes=3, per_plane=120, outlier_ratio=0.5))
    assert (len(sc.x1) <= Sampler.ALL_AT_ONCE) == small
    problem = build_problem(sc.x1, sc.x2, miho=True, full_match=True)
    cfg = FilterConfig()
    shared = LocalCandidates(problem, cfg, compiled=True)
    gen_ref, gen_got = np.random.default_rng(11), np.random.default_rng(11)
    pool = np.arange(len(sc.x1))
    for plane in range(3):
        ref = Sampler(problem, pool, cfg)
        got = Sampler(problem, pool, cfg, shared, compiled=True)
        for size in (128, 37, 512):
            np.testing.assert_array_equal(got.draw(gen_got, size), ref.draw(gen_ref, size))
            assert gen_got.random() == gen_ref.random()
        pool = pool[(sc.plane[pool] != plane) & (rng.random(len(pool)) < 0.8)]


@pytest.mark.parametrize("small", [False, True])
def test_local_inlier_fraction_in_one_call_is_the_same(small):
    """The adaptive bound's local inlier fraction (searches of the probes' lists, then the
    share of inliers among them), compiled in one call against the numpy sampler, between
    batches of draws over shrinking pools: the same fractions and the same draws after."""
    rng = np.random.default_rng(8)
    sc = (make_scene(rng, n_planes=2, per_plane=80, outlier_ratio=0.3) if small
          else make_scene(rng, n_planes=3, per_plane=150, outlier_ratio=0.5))
    assert (len(sc.x1) <= Sampler.ALL_AT_ONCE) == small
    problem = build_problem(sc.x1, sc.x2, miho=True, full_match=True)
    cfg = FilterConfig()
    shared = LocalCandidates(problem, cfg, compiled=True)
    gen_ref, gen_got = np.random.default_rng(12), np.random.default_rng(12)
    pool = np.arange(len(sc.x1))
    fractions = []
    for plane in range(3):
        ref = Sampler(problem, pool, cfg)
        got = Sampler(problem, pool, cfg, shared, compiled=True)
        for share in (0.9, 0.3, 0.05):  # masks of the pool's plane matches and some others
            mask = (sc.plane[pool] == plane) | (rng.random(len(pool)) < 0.1)
            mask &= rng.random(len(pool)) < share
            count = int(mask.sum())
            want = ref.local_inlier_fraction(mask, count)
            assert got.local_inlier_fraction(mask, count) == want
            fractions.append(want)
            np.testing.assert_array_equal(got.draw(gen_got, 64), ref.draw(gen_ref, 64))
        pool = pool[(sc.plane[pool] != plane) & (rng.random(len(pool)) < 0.8)]
    assert len(set(fractions)) > 3 and 0.5 < max(fractions) <= 1


@pytest.mark.parametrize("method", ["mop", "mop_miho"])
def test_whole_filter_agrees(method, monkeypatch):
    """The whole filter, compiled against numpy, on synthetic scenes."""
    cfg = FilterConfig(method=method)
    for seed in range(3):
        sc, _, _ = _problem(False, seed)
        got = filter_matches(sc.x1, sc.x2, config=cfg, seed=seed)
        with monkeypatch.context() as m:
            m.setattr(NumpyScoring.__init__, "__defaults__", (False,))  # the numpy reference
            m.setitem(choose_rotation.__kwdefaults__, "compiled", False)
            want = filter_matches(sc.x1, sc.x2, config=cfg, seed=seed)
        assert np.mean(got.inliers == want.inliers) >= SAME_FLAGS
        assert got.num_homographies == want.num_homographies


@pytest.mark.parametrize("miho", [False, True])
@pytest.mark.parametrize("pool_size", [60, 200, 330])
def test_neighbours_are_the_same(miho, pool_size):
    """The compiled search (problem-wide candidates, then an exhaustive search of the pool
    where too few of them are left) against the numpy one (k-d tree over the pool)."""
    sc, problem, rng = _problem(miho)
    cfg = FilterConfig()
    pool = np.sort(rng.choice(len(sc.x1), pool_size, replace=False))
    ref = Sampler(problem, pool, cfg)
    got = Sampler(problem, pool, cfg, compiled=True)
    pos = rng.permutation(pool_size)
    for part in np.array_split(pos, 3):  # searched over several calls, as the rounds do
        np.testing.assert_array_equal(got.neighbours(part), ref.neighbours(part))
    nb = ref.neighbours(np.arange(pool_size))
    assert (nb >= 0).any()


@pytest.mark.parametrize("miho", [False, True])
def test_singular_value_test_is_the_same(miho):
    cfg = FilterConfig(method="mop_miho" if miho else "mop")
    sc, problem, rng = _problem(miho)
    sample = _samples(sc, rng, 3000)
    hyp = hypotheses_from_samples(problem, sample, cfg)
    want = NumpyScoring(compiled=False).singular_value_ok(problem, hyp, cfg)
    assert 0 < want.sum() < len(want)
    got = NumpyScoring(compiled=True).singular_value_ok(problem, hyp, cfg)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("miho", [False, True])
@pytest.mark.parametrize("start", ["empty", "weak best", "strong best"])
def test_scoring_a_batch_in_one_call_is_the_same(miho, start):
    """The compiled batch scoring against the loop over groups of the numpy path: the same
    hypotheses scored, the same best, the same candidates in the same order."""
    from colmap_miho.filtering.ransac import _score_batch, _Search

    cfg = FilterConfig(method="mop_miho" if miho else "mop")
    sc, problem, rng = _problem(miho)
    hyp = hypotheses_from_samples(problem, _samples(sc, rng, 1500), cfg)
    pool = np.sort(rng.choice(len(sc.x1), 2 * len(sc.x1) // 3, replace=False))
    ref = NumpyScoring(compiled=False)
    ub = ref.one_way_count(problem, hyp, pool, cfg.t_l**2)
    searches = []
    for scoring in (ref, NumpyScoring(compiled=True)):
        search = _Search(t2=cfg.t_l**2)
        if start != "empty":  # a best from an earlier batch, weaker or stronger than most
            prior = hyp.take([0])
            search.hyp, search.count = prior, int(np.quantile(ub, 0.9 if start == "weak best"
                                                              else 0.999))
            search.mask = np.zeros(len(pool), dtype=bool)
            search.mask[: search.count] = True
        stats = {"full_scored": 0}
        improved = _score_batch(problem, hyp, ub, pool, cfg, search, stats, scoring)
        searches.append((search, stats, improved))
    (want, want_stats, want_imp), (got, got_stats, got_imp) = searches
    assert want_stats["full_scored"] > 0 and len(want.cands) > 2
    assert (got_imp, got_stats, got.count) == (want_imp, want_stats, want.count)
    np.testing.assert_array_equal(got.mask, want.mask)
    np.testing.assert_array_equal(got.hyp.H, want.hyp.H)
    assert len(got.cands) == len(want.cands)
    for (gh, gr, gm), (wh, wr, wm) in zip(got.cands, want.cands, strict=True):
        np.testing.assert_array_equal(gh.row(gr).H, wh.row(wr).H)
        np.testing.assert_array_equal(gh.row(gr).sample, wh.row(wr).sample)
        np.testing.assert_array_equal(gm, wm)


def test_a_row_is_the_take_of_it():
    cfg = FilterConfig()
    sc, problem, rng = _problem(False)
    hyp = hypotheses_from_samples(problem, _samples(sc, rng), cfg)
    for k in (0, len(hyp) // 2, len(hyp) - 1):
        one, want = hyp.row(k), hyp.take([k])
        for f in ("H", "Hinv", "sign", "sign_inv", "sample"):
            np.testing.assert_array_equal(getattr(one, f), getattr(want, f))
            assert getattr(one, f).shape == getattr(want, f).shape


@pytest.mark.parametrize("miho", [False, True])
def test_refit_matches_numpy(miho):
    """The least-squares refit of the best model: the same acceptance, homographies up to
    their sign (an eigenvector's sign is arbitrary) to ``REFIT_ATOL``, the same inliers."""
    cfg = FilterConfig(method="mop_miho" if miho else "mop")
    sc, problem, rng = _problem(miho)
    hyp = hypotheses_from_samples(problem, _samples(sc, rng), cfg)
    pool = np.arange(len(sc.x1))
    masks = NumpyScoring(compiled=False).masks(problem, hyp, pool, cfg.t_l**2)[0]
    fitted = 0
    for k in np.flatnonzero(masks.sum(axis=1) >= 5)[:150]:
        want = _refit(problem, hyp.take(k), pool[masks[k]])
        got = _refit(problem, hyp.take(k), pool[masks[k]], compiled=True)
        assert (got is None) == (want is None)
        if want is None:
            continue
        assert got is not None
        fitted += 1
        flip = np.sign(np.sum(got.H * want.H, axis=(2, 3)))[..., None, None]  # (1, halves)
        np.testing.assert_allclose(got.H * flip, want.H, rtol=0, atol=REFIT_ATOL)
        np.testing.assert_allclose(got.Hinv, want.Hinv, rtol=0, atol=REFIT_ATOL)
        np.testing.assert_array_equal(got.sign * flip[..., 0, 0], want.sign)
        ref = NumpyScoring(compiled=False)
        np.testing.assert_array_equal(ref.masks(problem, got, pool, cfg.t_l**2)[0],
                                      ref.masks(problem, want, pool, cfg.t_l**2)[0])
    assert fitted > 50


@pytest.mark.parametrize("reflections", [False, True])
def test_rotation_choice_is_the_same(reflections):
    """The rotation fix's counts, compiled against numpy: the same choice and count on
    turned, mirrored and upright scenes, with all pairs and with sampled pairs."""
    from colmap_miho.filtering.miho import choose_rotation

    for seed, (deg, mirror) in enumerate([(0, False), (90, False), (180, False), (270, True)]):
        sc = make_scene(np.random.default_rng(seed), per_plane=60, rotate_deg=deg, mirror=mirror)
        for pairs in (0, 5000):
            want = choose_rotation(sc.x1, sc.x2, np.random.default_rng(seed), pairs=pairs,
                                   reflections=reflections, compiled=False)
            got = choose_rotation(sc.x1, sc.x2, np.random.default_rng(seed), pairs=pairs,
                                  reflections=reflections, compiled=True)
            np.testing.assert_array_equal(got[0], want[0])
            assert got[1:] == want[1:] and want[2] > 0


@pytest.mark.parametrize("z", [0, 1, 5, 40])
def test_buffer_choice_is_the_same(z):
    """The compiled top-z buffer choice against the numpy greedy cover, on candidate masks
    with ties, empty rows and rows the best model covers, so that the cover stops early."""
    from colmap_miho.filtering.problem import Hypotheses
    from colmap_miho.filtering.ransac import _greedy_buffer

    rng = np.random.default_rng(z)
    hyp = Hypotheses(*(rng.normal(size=(30,) + s) for s in ((1, 3, 3), (1, 3, 3), (1,), (1,))),
                     rng.integers(0, 100, (30, 4)))
    masks = rng.random((30, 200)) < rng.uniform(0.0, 0.3, (30, 1))
    masks[3] = masks[7]  # a tie: the first wins
    masks[11] = False
    best = rng.random(200) < 0.4
    masks[12] = best  # covered entirely: never chosen
    cands = [(hyp, k, masks[k]) for k in range(30)]
    ref = _greedy_buffer(cands, best, z)
    got = _greedy_buffer(cands, best, z, compiled=True)
    assert len(got) == len(ref) <= z
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a.sample, b.sample)
    rows = ransac.greedy_cover(masks, best, z).tolist()
    assert 7 not in rows and 11 not in rows and 12 not in rows
    if z >= 5:
        assert len(rows) >= 5


@pytest.mark.parametrize("layout", ["scene", "duplicates", "line", "cluster", "tiny"])
def test_nearest_grid_is_the_k_d_tree(layout):
    """The compiled grid search against scipy's k-d tree: the same distances in the same
    order for every point (the squared distances summed as scipy sums them), and where the
    indices differ the points are equidistant; ties by index."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(1)
    sc, _, _ = _problem(False)
    feats = np.concatenate([sc.x1, sc.x2], axis=1)
    if layout == "duplicates":
        feats = np.concatenate([feats, feats[::3]])
    elif layout == "line":  # all on one horizontal line in image 1: a degenerate grid
        feats[:, 1] = 7.0
    elif layout == "cluster":  # a dense cluster and far outliers
        feats = np.concatenate([rng.normal(300, 2, (500, 4)), rng.uniform(0, 5000, (20, 4))])
    elif layout == "tiny":
        feats = feats[:5]
    q = min(len(feats), 33)
    d_ref, i_ref = cKDTree(feats).query(feats, k=q)
    got = sampling.NearestGrid(feats).query(np.arange(len(feats)), q)
    diff = feats[got] - feats[:, None]
    d2 = diff[..., 0] ** 2 + diff[..., 1] ** 2 + diff[..., 2] ** 2 + diff[..., 3] ** 2
    np.testing.assert_array_equal(np.sqrt(d2), d_ref.reshape(len(feats), q))
    assert np.all((np.diff(d2, axis=1) > 0) | ((np.diff(d2, axis=1) == 0) & (np.diff(got, axis=1) > 0)))
    if layout == "duplicates":
        assert (got != i_ref).any()  # ties in another order than the tree's
    part = rng.permutation(len(feats))[: max(1, len(feats) // 3)]
    np.testing.assert_array_equal(sampling.NearestGrid(feats).query(part, q), got[part])


@pytest.mark.parametrize("miho", [False, True])
def test_neighbours_of_a_small_problem_are_the_same(miho):
    """A problem of at most Sampler.ALL_AT_ONCE matches: the compiled sampler searches the
    pool exhaustively (no problem-wide candidates) and finds the numpy sampler's neighbours,
    on the whole problem and on a pool that earlier rounds thinned out."""
    rng = np.random.default_rng(4)
    sc = make_scene(rng, n_planes=2, per_plane=80, outlier_ratio=0.3)
    assert len(sc.x1) <= Sampler.ALL_AT_ONCE
    problem = build_problem(sc.x1, sc.x2, miho=miho, full_match=miho)
    cfg = FilterConfig()
    for pool in (np.arange(len(sc.x1)), np.sort(rng.choice(len(sc.x1), 60, replace=False))):
        ref = Sampler(problem, pool, cfg)
        got = Sampler(problem, pool, cfg, compiled=True)
        pos = np.arange(len(pool))
        want = ref.neighbours(pos)
        np.testing.assert_array_equal(got.neighbours(pos), want)
        assert (want >= 0).any() and got._cands is not None and got._cands._grid is None


@pytest.mark.parametrize("miho", [False, True])
def test_neighbours_kept_from_earlier_pools_are_the_same(miho):
    """The compiled search keeps each match's full list for the rounds' later pools (the
    problem's shared candidates): over a chain of shrinking pools, then a pool that is not
    a subset of the one before, every list equals the numpy search's on that pool alone."""
    sc, problem, rng = _problem(miho)
    cfg = FilterConfig()
    shared = LocalCandidates(problem, cfg, compiled=True)
    pools = [np.arange(len(sc.x1))]
    for plane in range(3):  # the rounds remove a plane's matches, and some others
        pool = pools[-1]
        pools.append(pool[(sc.plane[pool] != plane) & (rng.random(len(pool)) < 0.8)])
    pools.append(np.sort(rng.choice(len(sc.x1), 150, replace=False)))  # not a subset
    reused = 0
    for pool in pools:
        listed_before = shared._listed.copy()
        got = Sampler(problem, pool, cfg, shared, compiled=True)
        want = Sampler(problem, pool, cfg)
        pos = rng.permutation(len(pool))
        for part in np.array_split(pos, 2):
            np.testing.assert_array_equal(got.neighbours(part), want.neighbours(part))
        reused += int(listed_before[pool].sum())
    assert reused > 0  # the kept lists were offered (and the answers still agree)
    assert shared._listed.any()


def test_pool_arrays_gathered_at_once_are_the_per_half_ones():
    """The scoring's pool arrays: the stacked gather and the float32 first half, built
    before or after the per-half arrays, hold the same values."""
    from colmap_miho.filtering.scoring import _Scratch

    sc, problem, rng = _problem(True)
    pools = [np.sort(rng.choice(len(sc.x1), m, replace=False)) for m in (50, 200)]
    for first_stacked in (True, False):
        work = _Scratch()
        for pool in pools:
            if first_stacked:
                stacked, p32 = work.stacked(problem, pool), work.points32(problem, pool)
            pts = work.points(problem, pool)
            if not first_stacked:
                p32, stacked = work.points32(problem, pool), work.stacked(problem, pool)
            want = np.stack([np.stack(p) for p in pts])
            assert stacked.flags.c_contiguous and stacked.shape == (problem.num_halves, 2, 2,
                                                                    len(pool))
            np.testing.assert_array_equal(stacked, want)
            for got, half in zip(p32, pts[0], strict=True):
                assert got.dtype == np.float32
                np.testing.assert_array_equal(got, half.astype(np.float32))


def _kernel_modules() -> tuple:
    """The modules of filtering/compiled/."""
    import importlib
    import pkgutil

    return tuple(importlib.import_module(f"{filter_compiled.__name__}.{m.name}")
                 for m in pkgutil.iter_modules(filter_compiled.__path__))


def test_compiled_modules_import_nothing_of_the_package():
    """filtering/compiled/ sits under the filter's modules, which import it: its modules
    import no module of colmap_miho but the kernel loader, itself a leaf (the warm-up, which
    filters a pair through the API, lives in preload.py), and so no kernel calls a jitted
    function of another file (numba's cache would not notice a change there)."""
    import ast
    import inspect

    from colmap_miho import compiled

    kernel_modules = _kernel_modules()
    for module in (*kernel_modules, compiled):
        for node in ast.walk(ast.parse(inspect.getsource(module))):
            loader = isinstance(node, ast.ImportFrom) and (node.level, node.module) == (3, "compiled")
            if module is not compiled and loader:
                continue
            if isinstance(node, ast.ImportFrom):
                assert node.level == 0 and not (node.module or "").startswith("colmap_miho"), ast.unparse(node)
            elif isinstance(node, ast.Import):
                assert not any(a.name.startswith("colmap_miho") for a in node.names), ast.unparse(node)
    for module in kernel_modules:
        assert not hasattr(module, "warm")


def test_preload_warm_loads_the_kernels():
    from colmap_miho.filtering import preload

    assert preload.warm()
    assert all(m.KERNELS.loaded for m in _kernel_modules())
