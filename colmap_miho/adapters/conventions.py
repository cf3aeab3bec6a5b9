"""COLMAP's conventions converted in one place: the half-pixel offset of keypoints (COLMAP's
top-left pixel centre is (0.5, 0.5), colmap-miho's (0, 0)) and the pair id of two image ids."""

from __future__ import annotations

import numpy as np

from ..types import Pair

HALF_PIXEL = 0.5


MAX_IMAGE_ID = 2147483647


def colmap_to_pixel_centre(xy: np.ndarray) -> np.ndarray:
    """COLMAP keypoint coordinates (N, 2) -> colmap-miho's (integer = pixel centre), float64."""
    return np.asarray(xy, dtype=np.float64) - HALF_PIXEL


def pixel_centre_to_colmap(xy: np.ndarray) -> np.ndarray:
    """colmap-miho coordinates (N, 2) (integer = pixel centre) -> COLMAP's, float64."""
    return np.asarray(xy, dtype=np.float64) + HALF_PIXEL


def pair_id(image_id1: int, image_id2: int) -> int:
    """COLMAP's pair id: 2147483647 * min + max."""
    a, b = sorted((int(image_id1), int(image_id2)))
    return MAX_IMAGE_ID * a + b


def image_pair(pid: int) -> Pair:
    """Inverse of :func:`pair_id`: (smaller image id, larger image id)."""
    pid = int(pid)
    return pid // MAX_IMAGE_ID, pid % MAX_IMAGE_ID


#: Pixels a keypoint may lie outside its image (sub-pixel refinement near the border moves a
#: keypoint a little past it); farther, it is not a measurement of that image.
KEYPOINT_MARGIN_PX = 2.0
