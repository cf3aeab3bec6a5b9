"""Types shared across the package."""

from __future__ import annotations

import numpy as np

#: An image pair ``(image_id1, image_id2)`` with ``image_id1 < image_id2``.
Pair = tuple[int, int]

#: A ``cam_from_world`` pose: rotation ``(3, 3)``, translation ``(3,)`` (``X_cam = R X + t``).
Pose = tuple[np.ndarray, np.ndarray]
