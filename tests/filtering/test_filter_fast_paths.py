"""The fast numpy paths of the filter give the same bits and decisions as the plain formulas
they replace (term-by-term inlier masks, fused transfer error, written-out small sums,
the rotation fix's shared squares, screening ahead)."""

from __future__ import annotations

import numpy as np
import pytest
from planes import assert_same_mop_runs, make_scene

from colmap_miho.filtering.config import FilterConfig
from colmap_miho.filtering.homography import _dlt_system, dlt, project
from colmap_miho.filtering.miho import (
    _ROTATION_Z,
    _candidate_transforms,
    _differences,
    _norms,
    build_problem,
    choose_rotation,
)
from colmap_miho.filtering.problem import Hypotheses, Problem
from colmap_miho.filtering.ransac import _refit
from colmap_miho.filtering.sampling import apart_sets, spread_ok
from colmap_miho.filtering.scoring import (
    NumpyScoring,
    error_sq,
    hypotheses_from_samples,
    inlier_masks,
)


def _reference_error_sq(problem: Problem, hyp: Hypotheses, idx: np.ndarray) -> np.ndarray:
    """The plain formula: project, squared difference, inf where the sign breaks, max."""
    err = np.zeros((len(hyp), len(idx)))
    for h in range(problem.num_halves):
        src, dst = problem.src[h][idx], problem.dst[h][idx]
        for mat, sgn, a, b in ((hyp.H, hyp.sign, src, dst), (hyp.Hinv, hyp.sign_inv, dst, src)):
            x, y, w = project(mat[:, h], a)
            e = (x - b[:, 0]) ** 2 + (y - b[:, 1]) ** 2
            e[np.sign(w) != sgn[:, h, None]] = np.inf
            np.maximum(err, e, out=err)
    return err * problem.error_scale**2


def _hypotheses(problem: Problem, rng: np.random.Generator, n: int) -> Hypotheses:
    sample = rng.integers(0, len(problem.x1), (n, 4))
    cfg = FilterConfig(method="mop")
    hyp = hypotheses_from_samples(problem, sample, cfg, np.ones(n, dtype=bool))
    assert len(hyp) >= n // 10  # random samples: most break quasi-affinity
    return hyp


@pytest.mark.parametrize("miho,scale", [(False, 1.0), (True, 1.0), (True, 2.0), (True, 1.5)])
def test_error_and_masks_match_the_plain_formula(miho, scale):
    sc = make_scene(np.random.default_rng(3), outlier_ratio=0.5)
    base = build_problem(sc.x1, sc.x2, miho=miho)
    problem = Problem(src=base.src, dst=base.dst, spread=base.spread, x1=base.x1, x2=base.x2,
                      error_scale=scale)
    hyp = _hypotheses(problem, np.random.default_rng(1), 1000)
    idx = np.sort(np.random.default_rng(2).choice(len(sc.x1), len(sc.x1) // 2, replace=False))
    ref = _reference_error_sq(problem, hyp, idx)
    np.testing.assert_array_equal(error_sq(problem, hyp, idx), ref)
    # Random samples: many projections break the sample's sign (inf), all kinds of masks.
    assert np.isinf(ref).any() and 0 < np.mean(ref <= 15.0**2) < 0.9
    for t in (0.5, 3.0, 15.0, 200.0):
        np.testing.assert_array_equal(inlier_masks(problem, hyp, idx, t * t), ref <= t * t)


def test_apart_and_spread_test_match_the_reductions():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, (500, 4, 3, 2))
    d = pts[:, 0] - pts[:, 1]
    np.testing.assert_array_equal(apart_sets(np.moveaxis(d[..., 0], -1, 0).copy(),
                                              np.moveaxis(d[..., 1], -1, 0).copy(), 30.0**2),
                                  np.all((d * d).sum(-1) >= 30.0**2, axis=-1))
    sc = make_scene(rng)
    problem = build_problem(sc.x1, sc.x2, miho=True)
    sample = rng.integers(0, len(sc.x1), (2000, 4))
    p = problem.spread_all[sample]
    pi, pj = np.array([0, 0, 0, 1, 1, 2]), np.array([1, 2, 3, 2, 3, 3])
    dd = p[:, pi] - p[:, pj]
    ref = np.all((dd * dd).sum(-1) >= 60.0**2, axis=(1, 2))
    assert 0.05 < ref.mean() < 0.95
    np.testing.assert_array_equal(spread_ok(problem, sample, 60.0), ref)


def _reference_rotation(x1, x2, rng, pairs, reflections):
    """The rotation fix's counts with the full 2x2 products (before the shared squares)."""
    N = len(x1)
    i = rng.integers(0, N, pairs)
    j = rng.integers(0, N, pairs)
    keep = i != j
    i, j = i[keep], j[keep]
    dx1, dx2 = x1[i] - x1[j], x2[i] - x2[j]
    d1, d2 = np.sqrt((dx1**2).sum(1)), np.sqrt((dx2**2).sum(1))
    lo, hi = np.minimum(d1, d2) - 1e-9, np.maximum(d1, d2) + 1e-9
    cands = _candidate_transforms(x2, reflections)
    R = np.stack([G[:2, :2] for G in cands])[:, :, :, None]
    mx = dx1[:, 0] + R[:, 0, 0] * dx2[:, 0] + R[:, 0, 1] * dx2[:, 1]
    my = dx1[:, 1] + R[:, 1, 0] * dx2[:, 0] + R[:, 1, 1] * dx2[:, 1]
    dm = np.sqrt(mx * mx + my * my) / 2
    inside = (dm >= lo) & (dm <= hi)
    scores = inside.sum(1)
    diff = inside.astype(np.int64) - inside[0]
    z = (scores - scores[0]) / np.sqrt(np.maximum((diff * diff).sum(1), 1))
    clear = np.flatnonzero(z > _ROTATION_Z)
    best = int(clear[np.argmax(scores[clear])]) if len(clear) else 0
    return best, int(scores[best])


@pytest.mark.parametrize("rotate,mirror", [(0, False), (90, False), (180, False), (270, True)])
def test_rotation_fix_matches_the_full_products(rotate, mirror):
    sc = make_scene(np.random.default_rng(7), rotate_deg=rotate, mirror=mirror,
                    outlier_ratio=0.3)
    _, idx, score = choose_rotation(sc.x1, sc.x2, np.random.default_rng(0), pairs=20000,
                                    reflections=True)
    assert (idx, score) == _reference_rotation(sc.x1, sc.x2, np.random.default_rng(0), 20000, True)
    assert (idx != 0) == (rotate != 0 or mirror)  # the fix did turn the turned scenes


@pytest.mark.parametrize("scale", [1.0, 1500.0, 1e7])
def test_rotation_pair_differences_and_norms_match_the_row_formulas(scale):
    rng = np.random.default_rng(5)
    x = rng.uniform(-scale, scale, (3000, 2))
    i, j = rng.integers(0, 3000, 100000), rng.integers(0, 3000, 100000)
    d = x[i] - x[j]
    np.testing.assert_array_equal(_differences(x, i, j), d.T)
    np.testing.assert_array_equal(_norms(d.T.copy()), np.sqrt((d**2).sum(1)))


def test_dlt_system_blocks_match_the_stacked_rows():
    rng = np.random.default_rng(4)
    s, d = rng.normal(size=(300, 4, 2)), rng.normal(size=(300, 4, 2))
    s[0, 0], d[1, 2] = 0.0, -0.0  # signed zeros keep their sign
    x, y, u, v = s[..., 0], s[..., 1], d[..., 0], d[..., 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    even = np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], axis=-1)
    odd = np.stack([zero, zero, zero, x, y, one, -v * x, -v * y, -v], axis=-1)
    ref = np.stack([even, odd], axis=2).reshape(300, 8, 9)
    # bit for bit (signed zeros included)
    np.testing.assert_array_equal(_dlt_system(s, d).view(np.int64), ref.view(np.int64))


def test_refit_of_both_halves_in_one_batch_matches_one_fit_per_half():
    sc = make_scene(np.random.default_rng(8), outlier_ratio=0.3)
    problem = build_problem(sc.x1, sc.x2, miho=True, full_match=True)
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(40):
        idx = rng.choice(len(sc.x1), size=int(rng.integers(5, 300)), replace=False)
        hyp = hypotheses_from_samples(problem, idx[None, :4], FilterConfig())
        if not len(hyp):
            continue
        checked += 1
        refit = _refit(problem, hyp, idx)
        assert refit is not None
        for h in range(problem.num_halves):  # bit for bit
            one = dlt(problem.src[h][idx][None], problem.dst[h][idx][None])[0][0]
            np.testing.assert_array_equal(refit.H[0, h], one)
    assert checked >= 10


class _Exact(NumpyScoring):
    prefetch = 0  # scores exactly the hypotheses the search reaches


@pytest.mark.parametrize("method", ["mop", "mop_miho"])
def test_default_screening_ahead_gives_the_exact_search(method):
    assert NumpyScoring.prefetch > 0
    assert_same_mop_runs(method, NumpyScoring(), _Exact(), scene_seed=11, outlier_ratio=0.6)
