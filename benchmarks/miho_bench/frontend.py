"""Offline matching front ends of the paper's evaluation (OpenCV only, no downloads).

* ``detector="sift"``: OpenCV SIFT, RootSIFT descriptors, upright (orientation 0), mutual
  nearest neighbour with Lowe ratio 0.95 - the paper's "SIFT+NNR".
* ``detector="gftt"``: corner-like keypoints (Shi-Tomasi / GFTT) described by the same
  RootSIFT descriptor at a fixed scale, same matching - a corner-like front end on which NCC
  refinement is expected to help.

Coordinates are OpenCV's: (x, y) pixels, integer = pixel centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrontendMatches:
    """Tentative matches of one image pair.

    Attributes:
        pts1, pts2: (N, 2) float64 pixel coordinates of the matched keypoints.
        affine1, affine2: (N, 2, 2) local frames of the keypoints (the matrix mapping a unit
            canonical patch offset to image pixels: scale * rotation), or None.
        scores: (N,) ratio of best to second-best descriptor distance (lower is better).
        num_keypoints: keypoints detected in each image.
    """

    pts1: np.ndarray
    pts2: np.ndarray
    affine1: np.ndarray | None
    affine2: np.ndarray | None
    scores: np.ndarray
    num_keypoints: tuple[int, int]

    def __len__(self) -> int:
        return len(self.pts1)


def _rootsift(desc: np.ndarray) -> np.ndarray:
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(desc)


def detect_and_describe(image: np.ndarray, *, detector: str = "sift", max_features: int = 8000,
                        rootsift: bool = True, upright: bool = True, gftt_size: float = 12.0):
    """Keypoints and descriptors of one (H, W) uint8 grayscale image.

    Returns:
        (pts (N, 2) float64, frames (N, 2, 2) float64, descriptors (N, 128) float32).
    """
    import cv2

    if image.ndim != 2:
        raise ValueError(f"image must be (H, W) grayscale, got shape {image.shape}")
    image = np.ascontiguousarray(image, dtype=np.uint8)
    sift = cv2.SIFT_create(nfeatures=max_features)
    if detector == "sift":
        kps = sift.detect(image, None)
    elif detector == "gftt":
        corners = cv2.goodFeaturesToTrack(image, maxCorners=max_features, qualityLevel=0.001,
                                          minDistance=3, blockSize=5)
        corners = np.zeros((0, 1, 2), np.float32) if corners is None else corners
        kps = [cv2.KeyPoint(float(x), float(y), gftt_size) for x, y in corners.reshape(-1, 2)]
    else:
        raise ValueError(f"detector must be 'sift' or 'gftt', got {detector!r}")
    if upright:
        unique = {}
        for kp in kps:  # SIFT duplicates a keypoint per orientation: keep one, angle 0
            key = (round(kp.pt[0], 3), round(kp.pt[1], 3), round(kp.size, 3))
            if key not in unique:
                unique[key] = cv2.KeyPoint(kp.pt[0], kp.pt[1], kp.size, 0.0, kp.response, kp.octave)
        kps = list(unique.values())
    if not kps:
        return np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 128), np.float32)
    kps, desc = sift.compute(image, kps)
    if desc is None:
        return np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 128), np.float32)
    pts = np.array([kp.pt for kp in kps], dtype=np.float64)
    scale = np.array([kp.size / 2.0 for kp in kps])
    angle = np.deg2rad([kp.angle if kp.angle >= 0 else 0.0 for kp in kps])
    c, s = np.cos(angle), np.sin(angle)
    frames = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2) * scale[:, None, None]
    return pts, frames, (_rootsift(desc) if rootsift else desc.astype(np.float32))


def mutual_nn_ratio(desc1: np.ndarray, desc2: np.ndarray, ratio: float = 0.95):
    """Mutual nearest neighbours passing Lowe's ratio test (on distances) in both directions.

    Returns:
        (idx (M, 2) int64 indices into desc1/desc2, scores (M,) distance ratio).
    """
    import cv2

    if len(desc1) < 2 or len(desc2) < 2:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(desc1, desc2, k=2)
    bwd = bf.knnMatch(desc2, desc1, k=2)
    best12 = np.array([m[0].trainIdx for m in fwd])
    r12 = np.array([m[0].distance / max(m[1].distance, 1e-12) for m in fwd])
    best21 = np.array([m[0].trainIdx for m in bwd])
    r21 = np.array([m[0].distance / max(m[1].distance, 1e-12) for m in bwd])
    i = np.arange(len(desc1))
    keep = (best21[best12] == i) & (r12 < ratio) & (r21[best12] < ratio)
    idx = np.stack([i[keep], best12[keep]], axis=1).astype(np.int64)
    return idx, r12[keep]


def sift_matches(img1: np.ndarray, img2: np.ndarray, *, detector: str = "sift", max_features: int = 8000,
                 ratio: float = 0.95, rootsift: bool = True, upright: bool = True) -> FrontendMatches:
    """Match two (H, W) uint8 grayscale images with the chosen offline front end."""
    p1, f1, d1 = detect_and_describe(img1, detector=detector, max_features=max_features,
                                     rootsift=rootsift, upright=upright)
    p2, f2, d2 = detect_and_describe(img2, detector=detector, max_features=max_features,
                                     rootsift=rootsift, upright=upright)
    idx, scores = mutual_nn_ratio(d1, d2, ratio)
    return FrontendMatches(p1[idx[:, 0]], p2[idx[:, 1]], f1[idx[:, 0]], f2[idx[:, 1]], scores, (len(p1), len(p2)))


def filtered_multiview_matches(images: dict, *, detector: str = "sift", max_features: int = 8000,
                               ratio: float = 0.95, method: str = "mop_miho",
                               min_inliers: int = 8):
    """Inputs of :func:`colmap_miho.refine_tracks` for a few images: keypoints, and for every
    image pair the mutual-NN ratio matches kept by the filter (``method``).

    Args:
        images: image_id -> (H, W) uint8 grayscale image.
    Returns:
        (keypoints: id -> (N, 2), matches: (id1, id2) -> (M, 2) keypoint indices of the kept
        matches, results: (id1, id2) -> FilterResult restricted to the kept rows, 1:1 with
        the matches); pairs whose filter failed or kept fewer
        than ``min_inliers`` matches are left out.
    """
    import dataclasses
    import itertools

    from colmap_miho.filtering.api import filter_matches

    feats = {i: detect_and_describe(im, detector=detector, max_features=max_features)
             for i, im in images.items()}
    keypoints = {i: f[0] for i, f in feats.items()}
    matches, results = {}, {}
    for i, j in itertools.combinations(sorted(images), 2):
        idx, _ = mutual_nn_ratio(feats[i][2], feats[j][2], ratio)
        fr = filter_matches(keypoints[i][idx[:, 0]], keypoints[j][idx[:, 1]], method=method)
        if fr.success and fr.inliers.sum() >= min_inliers:
            keep = np.asarray(fr.inliers, bool)  # results' rows 1:1 with the kept matches
            matches[(i, j)] = idx[keep]
            results[(i, j)] = dataclasses.replace(fr, inliers=fr.inliers[keep], labels=fr.labels[keep])
    return keypoints, matches, results
