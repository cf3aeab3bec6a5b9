"""The filter profiling benchmarks add up the filter's own RANSAC counters."""

from __future__ import annotations

import numpy as np
from bench_filter_scenes import COUNTERS, Pair, run_pass
from bench_hard_pairs import print_profile
from planes import make_scene

from colmap_miho import filter_matches
from colmap_miho.filtering.config import FilterConfig


def test_run_pass_sums_the_counters_of_every_pair(capsys):
    scenes = [make_scene(np.random.default_rng(s), outlier_ratio=0.5) for s in (1, 2)]
    pairs = [Pair(sc.x1, sc.x2, seed=7 + k) for k, sc in enumerate(scenes)]
    configs = {"fast": FilterConfig(batch_growth=2, max_iters=None), "default": FilterConfig()}
    out = run_pass(pairs, configs)
    for name, cfg in configs.items():
        results = [filter_matches(p.pts1, p.pts2, config=cfg, seed=p.seed) for p in pairs]
        for key in COUNTERS:
            assert out[name][key] == sum(r.stats[key] for r in results)
        assert out[name]["kept"] == sum(r.num_inliers for r in results)
        assert out[name]["cpu"] > 0
    # the cap of 500 per round draws fewer samples than 2000 on these pairs
    assert out["fast"]["samples"] < out["default"]["samples"]
    print_profile({"x": [{"rounds": 4, "drawn": 10, "cpu": 0.02}]})
    assert "| x | 1 | 4.0 | 10.0 | 0.0 | 0.0 | 0.0 | 20.0 | 5.00 |" in capsys.readouterr().out


def test_numpy_kernel_variant_keeps_the_same_matches():
    """A ``kernels=numpy`` variant runs the reference kernels on the same pairs: the same
    kept matches here, and the compiled kernels are back in place after the pass."""
    from colmap_miho.filtering.compiled import scoring as kernels
    from colmap_miho.filtering.scoring import NumpyScoring

    sc = make_scene(np.random.default_rng(3), outlier_ratio=0.5)
    pairs = [Pair(sc.x1, sc.x2, seed=11)]
    calls = {"compiled": 0}
    real = kernels.hypotheses

    def counted(*args, **kwargs):
        calls["compiled"] += 1
        return real(*args, **kwargs)

    kernels.hypotheses = counted
    try:
        run_pass(pairs, {"numpy": FilterConfig()}, frozenset({"numpy"}))
        assert calls["compiled"] == 0  # the numpy variant never reaches a compiled kernel
        out = run_pass(pairs, {"default": FilterConfig(), "numpy": FilterConfig()}, frozenset({"numpy"}))
        assert calls["compiled"] > 0
    finally:
        kernels.hypotheses = real
    assert NumpyScoring().compiled  # the defaults are back
    np.testing.assert_array_equal(out["numpy"]["masks"][0], out["default"]["masks"][0])
    assert out["numpy"]["kept"] == out["default"]["kept"] > 0
