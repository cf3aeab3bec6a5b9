"""The match check's estimator: what it asks of a global estimate of the cameras and of the
estimator that makes one (:class:`colmap_miho.sfm.global_estimate.GlobalEstimator` is the
product's); the check and its hinge resolution both read it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, TypeVar

import numpy as np

from ..types import Pair, Pose


class CameraEstimate(Protocol):
    """What the judging reads of a global estimate (see :class:`~colmap_miho.sfm.global_estimate.GlobalEstimate`)."""

    @property
    def poses(self) -> Mapping[int, Pose]: ...
    @property
    def rays(self) -> Mapping[int, np.ndarray]: ...
    @property
    def focal(self) -> Mapping[int, float]: ...
    @property
    def pair_rotations(self) -> Mapping[Pair, np.ndarray]: ...
    @property
    def observations(self) -> Mapping[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]: ...
    @property
    def seconds(self) -> Mapping[str, float]: ...
    @property
    def mapper_steps(self) -> Mapping[str, float]: ...
    @property
    def failure(self) -> str: ...


Est = TypeVar("Est", bound=CameraEstimate)


class Estimator(Protocol[Est]):
    """Makes the global estimate from matches, and places one image again from its trusted part."""

    def estimate(self, matches: Mapping[Pair, np.ndarray]) -> Est:
        """The estimate from ``matches`` (pair -> int ``(M, 2)`` keypoint indices)."""

    def place(self, estimate: Est, image_id: int, matches: Mapping[Pair, np.ndarray],
              trusted: frozenset[int], min_inliers: int | None = None) -> Pose | None:
        """A new pose of ``image_id`` from ``estimate``'s points seen through the ``trusted``
        images; None when fewer than ``min_inliers`` inliers."""
