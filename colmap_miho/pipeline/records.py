"""Records that pass between the pipeline's stages: one filtered pair's outcome, as the filter
stage stores it and the refine and write stages read it back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..filtering.api import FilterResult
from ..types import Pair


@dataclass(frozen=True)
class PairOutcome:
    """What the later stages need of one pair's :class:`~colmap_miho.filtering.api.FilterResult`:
    ``inliers`` ``(M,)``, ``labels`` ``(M,)`` (-1: discarded), ``patch_homographies`` ``(K, 2, 3,
    3)`` and ``success`` (else written back unchanged)."""

    inliers: np.ndarray
    labels: np.ndarray
    patch_homographies: np.ndarray
    success: bool

    @classmethod
    def of(cls, r: FilterResult) -> PairOutcome:
        return cls(inliers=np.asarray(r.inliers, bool), labels=np.asarray(r.labels, np.int64),
                   patch_homographies=np.asarray(r.patch_homographies, np.float64).reshape(-1, 2, 3, 3),
                   success=bool(r.success))


#: (image_id1, image_id2) -> (matches uint32 ``(M, 2)`` keypoint indices, the pair's outcome)
FilteredPairs = dict[Pair, tuple[np.ndarray, PairOutcome]]
