"""The paper's match metrics (averaged precision/recall, homography error/AUC) and the peers."""

import sys

import numpy as np
import pytest

from miho_bench.peers import adalam_mask, colmap_verification_mask, gms_available, magsac_mask
from miho_bench.protocol import (
    averaged_precision_recall,
    homography_auc,
    homography_error,
    homography_from_matches,
)


def test_averaged_precision_recall_by_hand():
    # errors 0.5 (inlier at all t), 4.5 (inlier for t >= 5: 12 of 16 thresholds), 100 (never)
    err = np.array([0.5, 4.5, 100.0])
    kept = np.array([True, False, True])
    p, r = averaged_precision_recall(err, kept)
    # precision is 1/2 at every threshold; recall is 1/1 for t < 5 and 1/2 for t >= 5
    assert p == pytest.approx(0.5)
    assert r == pytest.approx((4 * 1.0 + 12 * 0.5) / 16)
    assert averaged_precision_recall(err, np.zeros(3, bool))[0] == 0.0
    with pytest.raises(ValueError, match="share one shape"):
        averaged_precision_recall(err, kept[:2])


def test_homography_error_is_zero_for_gt_and_grows_with_a_shift():
    H = np.array([[1.0, 0.1, 5.0], [0.0, 1.1, -3.0], [0.0, 1e-4, 1.0]])
    assert homography_error(H, H, (200, 300), (200, 300)) < 1e-9
    shifted = np.array([[1, 0, 2.0], [0, 1, 0], [0, 0, 1]]) @ H
    assert homography_error(shifted, H, (200, 300), (200, 300)) == pytest.approx(2.0, abs=0.2)
    assert homography_error(None, H, (200, 300), (200, 300)) == np.inf
    # errors [1, inf] at threshold 5: the curve rises to 1/2 at 1 px, area (4.5 * 0.5 + 0.25) / 5
    assert homography_auc([1.0, np.inf])["auc5"] == pytest.approx((0.5 * 1 * 0.5 + 4 * 0.5) / 5)


def _planar_matches(n=200, outliers=80, seed=0):
    rng = np.random.default_rng(seed)
    H = np.array([[0.9, 0.05, 20.0], [-0.04, 1.05, 10.0], [1e-5, 2e-5, 1.0]])
    pts1 = rng.uniform(0, 600, (n, 2))
    p = np.c_[pts1, np.ones(n)] @ H.T
    pts2 = p[:, :2] / p[:, 2:] + rng.normal(0, 0.3, (n, 2))
    pts2[:outliers] = rng.uniform(0, 600, (outliers, 2))
    truth = np.arange(n) >= outliers
    return pts1, pts2, truth, H


def test_peers_separate_planted_outliers():
    pts1, pts2, truth, H = _planar_matches()
    found = homography_from_matches(pts1[truth], pts2[truth])
    assert homography_error(found, H, (600, 600), (600, 600)) < 1.0
    for mask in (
        magsac_mask(pts1, pts2, planar=True, threshold_px=1.0),
        adalam_mask(pts1, pts2, np.full(len(pts1), 0.5), (600, 600), (600, 600)),
        colmap_verification_mask(pts1, pts2, (600, 600), (600, 600)),
    ):
        assert mask.shape == truth.shape
        precision = truth[mask].mean()
        recall = mask[truth].mean()
        assert precision > 0.9 and recall > 0.7, (precision, recall)
    assert magsac_mask(pts1[:5], pts2[:5]).sum() == 0
    assert isinstance(gms_available(), bool)


FAKE_REFERENCE = '''
import torch

calls = []


class miho:
    """Stands in for the authors' class: keeps the matches with x1 < {cut}, records the call."""

    def planar_clustering(self, pt1, pt2):
        calls.append((pt1.dtype, pt2.shape, torch.get_num_threads()))
        self.Hidx = torch.where(pt1[:, 0] < {cut}, 0, -1)
'''


def test_reference_runner_calls_the_authors_modules(tmp_path):
    """The side-by-side runner imports src/miho.py (MOP+MiHo) and src/miho_other.py (MOP) from
    the given checkout, calls them with float32 tensors and one torch thread, and keeps the
    matches they assign to a homography (a fake checkout: the reference is not shipped)."""
    import torch

    from miho_bench.peers import ReferenceMiho

    with pytest.raises(ImportError, match="fb82/MiHo"):
        ReferenceMiho(str(tmp_path))
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "__init__.py").write_text("")
    (tmp_path / "src" / "miho.py").write_text(FAKE_REFERENCE.format(cut=5))
    (tmp_path / "src" / "miho_other.py").write_text(FAKE_REFERENCE.format(cut=2))
    try:
        ref = ReferenceMiho(str(tmp_path))
        pts = np.stack([np.arange(8.0), np.zeros(8)], axis=1)
        threads = torch.get_num_threads()
        np.testing.assert_array_equal(ref.mask("mop_miho", pts, pts), np.arange(8) < 5)
        np.testing.assert_array_equal(ref.mask("mop", pts, pts), np.arange(8) < 2)
        assert ref.modules["mop_miho"].calls == [(torch.float32, (8, 2), 1)]
        assert torch.get_num_threads() == threads  # restored
    finally:
        for name in ("src", "src.miho", "src.miho_other"):
            sys.modules.pop(name, None)
