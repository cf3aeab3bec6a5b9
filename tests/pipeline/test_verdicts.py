"""The checks' verdicts (``pipeline.verdicts``): merged once, applied by one method."""

from __future__ import annotations

import numpy as np

from colmap_miho.pipeline.records import PairOutcome
from colmap_miho.pipeline.verdicts import NO_VERDICTS, Verdicts


def _pair(inliers: list[bool]):
    n = len(inliers)
    m = np.stack([np.arange(n), np.arange(n)], axis=1)
    labels = np.where(inliers, 0, -1).astype(np.int64)
    return m, PairOutcome(inliers=np.array(inliers), labels=labels, patch_homographies=np.zeros((1, 2, 3, 3)),
                          success=True)


def test_apply_drops_the_removed_pairs_and_the_failed_matches_in_order():
    pairs = {(1, 2): _pair([True, False, True, True]), (1, 3): _pair([True, True]), (2, 3): _pair([True])}
    v = Verdicts(removed=frozenset({(1, 3)}), failed={(1, 2): np.array([False, True, False])})
    out = v.apply(pairs)
    assert list(out) == [(1, 2), (2, 3)]
    assert out[(1, 2)][1].inliers.tolist() == [True, False, False, True]  # the second kept match failed
    assert out[(1, 2)][1].labels.tolist() == [0, -1, -1, 0]
    assert out[(2, 3)] is pairs[(2, 3)]
    assert pairs[(1, 2)][1].inliers.tolist() == [True, False, True, True]  # the stored pairs stay
    assert NO_VERDICTS.apply(pairs) == pairs
