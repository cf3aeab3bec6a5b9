"""The filter's torch path (``filter_matches(..., device=...)``) against the numpy path.

CUDA is not available in CI, so the torch path runs on the CPU (``device=torch.device("cpu")``):
the kernels, the chunked screening and the transfers are the ones CUDA runs. Where a GPU is
lent the same tests also run on ``"cuda"`` (``benchmarks/check_cuda.py --sections
filter,fountain`` prints the CPU vs CUDA figures).
Equivalence is measured as the share of matches with the same inlier flag and the same
label; only floating-point ties may differ. Measured (torch 2.13 CPU): identical flags,
labels and homographies (max difference 0) on every synthetic scene below and on Oxford
graf / boat / bikes 1->2 and 1->3 SIFT pairs, MOP and MOP+MiHo.
"""

from __future__ import annotations

import numpy as np
import pytest
from planes import assert_same_mop_runs, make_scene

from colmap_miho import filter_matches
from colmap_miho.enums import Device
from colmap_miho.filtering.config import FilterConfig
from colmap_miho.filtering.miho import build_problem
from colmap_miho.filtering.scoring import NumpyScoring, hypotheses_from_samples
from colmap_miho.filtering.torch_scoring import TorchScoring, scoring_for_device

torch = pytest.importorskip("torch")

MIN_AGREEMENT = 0.995  # share of matches with the same inlier flag / the same label
# The torch path on the CPU always; on CUDA too where a GPU is lent.
DEVICES = [torch.device("cpu")] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """The numpy filter is single-threaded; torch's CPU thread pool only adds contention
    on a shared 2-core runner (measured 100x slower small broadcasts with 2 busy threads)."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


def agreement(a, b) -> tuple[float, float]:
    """(same inlier flag, same label) shares of two :class:`FilterResult` s."""
    return float(np.mean(a.inliers == b.inliers)), float(np.mean(a.labels == b.labels))


# -- device argument ------------------------------------------------------------------------

def test_device_values_pick_the_kernels():
    assert type(scoring_for_device("cpu")) is NumpyScoring
    assert type(scoring_for_device(None)) is NumpyScoring
    assert type(scoring_for_device(Device.CPU)) is NumpyScoring  # the pipeline's enum
    auto = scoring_for_device("auto")
    assert isinstance(auto, TorchScoring) == torch.cuda.is_available()
    s = scoring_for_device(torch.device("cpu"))
    assert isinstance(s, TorchScoring) and s.device == torch.device("cpu")


@pytest.mark.parametrize("bad", ["gpu", "cuda:x", "torch-cpu", 3])
def test_bad_device_is_a_one_line_value_error(bad):
    with pytest.raises(ValueError, match="device") as info:
        filter_matches(np.zeros((10, 2)), np.zeros((10, 2)), device=bad)
    assert "\n" not in str(info.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_cuda_without_a_gpu_is_refused():
    with pytest.raises(ValueError, match="no CUDA device"):
        filter_matches(np.zeros((10, 2)), np.zeros((10, 2)), device="cuda")


# -- kernels ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def batch():
    """A MOP+MiHo problem (2 halves) of a synthetic scene, 768 minimal samples (a third
    within one plane), the
    hypotheses numpy fits to them, and a pool of 2/3 of the matches."""
    rng = np.random.default_rng(3)
    sc = make_scene(rng, n_planes=3, per_plane=120, outlier_ratio=0.5)
    problem = build_problem(sc.x1, sc.x2, miho=True, full_match=True)
    cfg = FilterConfig(method="mop_miho")
    plane0 = np.flatnonzero(sc.plane == 0)
    sample = np.concatenate([rng.integers(0, len(sc.x1), (512, 4)),
                             plane0[rng.integers(0, len(plane0), (256, 4))]])
    ok = np.ones(len(sample), dtype=bool)
    hyp = hypotheses_from_samples(problem, sample, cfg, ok)
    pool = np.sort(rng.choice(len(sc.x1), 2 * len(sc.x1) // 3, replace=False))
    return problem, cfg, sample, ok, hyp, pool


def _assert_nearly_equal(got, want, exact: bool):
    """Equal on the CPU; on CUDA at most 1% of entries off by one (float rounding ties)."""
    if exact:
        np.testing.assert_array_equal(got, want)
    else:
        diff = np.abs(np.asarray(got, dtype=np.int64) - np.asarray(want, dtype=np.int64))
        assert diff.max() <= 1 and np.mean(diff > 0) <= 0.01


@pytest.mark.parametrize("device", DEVICES)
def test_kernels_match_numpy(batch, device):
    problem, cfg, sample, ok, hyp, pool = batch
    ref = NumpyScoring()
    dev = scoring_for_device(device)
    exact = str(device) == "cpu"
    t2 = cfg.t_l**2
    got, got_bound = dev.hypotheses(problem, sample, cfg, ok, pool, t2)
    assert len(hyp) > 200 and len(got) == len(hyp)
    np.testing.assert_array_equal(got.sample, hyp.sample)
    np.testing.assert_array_equal(got.sign, hyp.sign)
    np.testing.assert_array_equal(got.sign_inv, hyp.sign_inv)
    np.testing.assert_allclose(got.H, hyp.H, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.Hinv, hyp.Hinv, rtol=0, atol=1e-12)
    bound = ref.one_way_count(problem, hyp, pool, t2)
    assert bound.max() > 50  # some hypotheses hit a plane: the counts are informative
    _assert_nearly_equal(got_bound, bound, exact)
    _assert_nearly_equal(dev.one_way_count(problem, hyp, pool, t2), bound, exact)
    sv_ref = ref.singular_value_ok(problem, hyp, cfg)
    assert 0 < sv_ref.sum() < len(sv_ref)  # the test rejects some, keeps most
    _assert_nearly_equal(dev.singular_value_ok(problem, hyp, cfg), sv_ref, exact)
    err_ref, err_dev = ref.error_sq(problem, hyp, pool), dev.error_sq(problem, hyp, pool)
    finite = np.isfinite(err_ref)
    np.testing.assert_array_equal(np.isfinite(err_dev), finite)
    np.testing.assert_allclose(err_dev[finite], err_ref[finite], rtol=1e-12, atol=1e-12)
    sv, masks = dev.screen(problem, hyp, pool, t2, cfg)
    _assert_nearly_equal(masks, err_ref <= t2, exact)
    _assert_nearly_equal(sv, sv_ref, exact)


class _Prefetching(NumpyScoring):
    prefetch = 3  # odd on purpose: chunks straddle the groups of 4


@pytest.mark.parametrize("method", ["mop", "mop_miho"])
def test_screening_ahead_gives_the_same_search(method):
    """Scoring hypotheses ahead in chunks (the device path's way) must not change what the
    search takes: numpy with and without prefetch give identical MOP runs."""
    assert_same_mop_runs(method, NumpyScoring(), _Prefetching(), scene_seed=5, outlier_ratio=0.5)


# -- whole filter -----------------------------------------------------------------------------

SCENES = {
    "upright": {},
    "rotated90": {"rotate_deg": 90},
    "mirrored": {"mirror": True},
    "outliers70": {"outlier_ratio": 0.7},
}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("method", ["mop", "mop_star", "mop_miho", "mop_miho_star", "mop_vsac"])
def test_torch_equals_numpy_on_planes(method, device):
    flags, labels = [], []
    for s, (name, kw) in enumerate(SCENES.items()):
        sc = make_scene(np.random.default_rng(10 + s), **kw)
        a = filter_matches(sc.x1, sc.x2, method=method, seed=s)
        b = filter_matches(sc.x1, sc.x2, method=method, seed=s, device=device)
        assert a.success == b.success, name
        if name != "mirrored" or "star" not in method:  # the star variants reject mirrors
            assert a.num_inliers > 0.5 * sc.is_inlier.sum(), name  # a real test, not empty
        f, lab = agreement(a, b)
        flags.append(f)
        labels.append(lab)
        if a.num_homographies == b.num_homographies:
            np.testing.assert_allclose(b.homographies, a.homographies, rtol=1e-6, atol=1e-9)
    assert min(flags) >= MIN_AGREEMENT, flags
    assert min(labels) >= MIN_AGREEMENT, labels


def test_torch_inputs_on_the_torch_path():
    sc = make_scene(np.random.default_rng(1))
    a = filter_matches(sc.x1, sc.x2, seed=2)
    b = filter_matches(torch.as_tensor(sc.x1), torch.as_tensor(sc.x2), seed=2,
                       device=torch.device("cpu"))
    assert isinstance(b.inliers, np.ndarray) and b.stats["rounds"] == a.stats["rounds"]
    assert agreement(a, b) == (1.0, 1.0)


# -- real pairs -------------------------------------------------------------------------------

REAL = [("graf", 2), ("graf", 3), ("boat", 2), ("bikes", 3)]


@pytest.fixture(scope="module")
def oxford_matches(shared_data):
    from miho_bench.datasets import oxford_pairs
    from miho_bench.frontend import sift_matches

    out = {}
    for seq, target in REAL:
        pair = oxford_pairs(shared_data / "oxford_affine" / seq, (target,))[0]
        fm = sift_matches(pair.image1(), pair.image2())
        out[(seq, target)] = (fm.pts1, fm.pts2)
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("method", ["mop", "mop_miho"])
def test_torch_equals_numpy_on_oxford(oxford_matches, method, device):
    total = same_flag = same_label = 0
    for key, (p1, p2) in oxford_matches.items():
        a = filter_matches(p1, p2, method=method, seed=0)
        b = filter_matches(p1, p2, method=method, seed=0, device=device)
        assert a.success and a.num_inliers > 0.3 * len(p1), key
        total += len(p1)
        same_flag += int(np.count_nonzero(a.inliers == b.inliers))
        same_label += int(np.count_nonzero(a.labels == b.labels))
    assert total > 3000
    assert same_flag / total >= MIN_AGREEMENT, same_flag / total
    assert same_label / total >= MIN_AGREEMENT, same_label / total


# -- the device check script --------------------------------------------------------------------

@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_check_cuda_exits_2_without_cuda(capsys):
    import check_cuda

    assert check_cuda.main(["--sections", "filter,fountain"]) == 2
    assert "no CUDA device" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        check_cuda.main(["--device", "cpu", "--sections", "filter,bogus"])
