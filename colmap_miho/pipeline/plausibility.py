"""Whether an image file is the one its keypoints were detected in: at a SIFT keypoint the DoG's
magnitude exceeds that a few scales away far more often than not; in another image (a file renamed
or shuffled after extraction) it is a coin toss."""

from __future__ import annotations

import math

import numpy as np

#: Keypoints sampled per image.
SAMPLE = 500
#: Fewer keypoints than this: no verdict (a smaller sample cannot tell a real image, whose share
#: lies 0.64-0.86 on the shared scenes, from chance at the margin below).
MIN_KEYPOINTS = SAMPLE
#: The share expected when keypoints and image are unrelated.
CHANCE = 0.5
#: Standard deviations above chance the share must reach (binomial over the sample).
MARGIN_SIGMAS = 4.0
#: Where the comparison point lies, in keypoint scales from the keypoint.
OFFSET_SCALES = 2.5
#: The DoG's second blur over its first (SIFT's scale step is 2^(1/3); 1.6 approximates the LoG).
DOG_RATIO = 1.6


def keypoint_support(image: np.ndarray, xy: np.ndarray, scale: np.ndarray | None, seed: int = 0
                     ) -> tuple[float, int]:
    """(share in [0, 1], keypoints sampled): sampled keypoints whose DoG magnitude exceeds that
    :data:`OFFSET_SCALES` scales away; ``scale`` ``(N,)`` pixels or None (1 px)."""
    import cv2

    n = len(xy)
    if n == 0:
        return 0.0, 0
    rng = np.random.default_rng(seed)
    idx = rng.choice(n, min(SAMPLE, n), replace=False)
    s = float(np.median(scale[idx])) if scale is not None else 1.0
    s = s if math.isfinite(s) and s > 0 else 1.0
    img = np.ascontiguousarray(image, np.float32)
    dog = np.abs(cv2.GaussianBlur(img, (0, 0), s) - cv2.GaussianBlur(img, (0, 0), DOG_RATIO * s))
    h, w = dog.shape
    angle = rng.uniform(0.0, 2.0 * np.pi, len(idx))
    p = xy[idx]
    q = p + OFFSET_SCALES * s * np.stack([np.cos(angle), np.sin(angle)], axis=1)

    def at(pts: np.ndarray) -> np.ndarray:
        c = np.clip(np.rint(pts[:, 0]), 0, w - 1).astype(np.int64)
        r = np.clip(np.rint(pts[:, 1]), 0, h - 1).astype(np.int64)
        return dog[r, c]

    return float(np.mean(at(p) > at(q))), len(idx)


def implausible(share: float, sampled: int) -> bool:
    """Whether ``share`` over ``sampled`` keypoints is indistinguishable from chance (no verdict
    below :data:`MIN_KEYPOINTS`)."""
    if sampled < MIN_KEYPOINTS:
        return False
    return share < CHANCE + MARGIN_SIGMAS * math.sqrt(CHANCE * (1 - CHANCE) / sampled)
