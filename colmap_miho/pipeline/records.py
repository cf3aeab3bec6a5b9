"""Records that pass between the pipeline's stages: one filtered pair's outcome, as the filter
stage stores it and the refine and write stages read it back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..filtering.api import FilterResult
from ..types import Pair


@dataclass(frozen=True)
class PairOutcome:
    """What the later stages need of one pair's :class:`~colmap_miho.filtering.api.FilterResult`
    (``FilterResult``-like for :func:`~colmap_miho.refinement.tracks.build.pair_rows`).

    Attributes:
        inliers: bool ``(M,)``, the matches kept (rows 1:1 with the pair's matches).
        labels: int64 ``(M,)``, each kept match's homography, -1 for discarded ones.
        patch_homographies: float64 ``(K, 2, 3, 3)``, see ``FilterResult``.
        success: a plane was found (otherwise the pair is written back unchanged).
    """

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
