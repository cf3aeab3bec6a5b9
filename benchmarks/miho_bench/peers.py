"""Peer match filters for the evaluation: MAGSAC, kornia's AdaLAM, OpenCV's GMS, COLMAP's
geometric verification. Each takes (N, 2) pixel-centre points and returns a (N,) bool mask.
"""

from __future__ import annotations

import numpy as np


def magsac_mask(pts1: np.ndarray, pts2: np.ndarray, *, planar: bool = False, threshold_px: float = 0.75,
                max_iters: int = 100000, seed: int = 0) -> np.ndarray:
    """``cv2.USAC_MAGSAC`` inliers of F (or of H for planar pairs) at ``threshold_px``."""
    import cv2

    n = len(pts1)
    need = 4 if planar else 8
    if n < need:
        return np.zeros(n, bool)
    p1, p2 = np.asarray(pts1, np.float64), np.asarray(pts2, np.float64)
    cv2.setRNGSeed(int(seed))
    try:
        if planar:
            _, mask = cv2.findHomography(p1, p2, cv2.USAC_MAGSAC, threshold_px, maxIters=max_iters, confidence=0.99999)
        else:
            _, mask = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, threshold_px, 0.99999, max_iters)
    except cv2.error:
        return np.zeros(n, bool)
    return np.zeros(n, bool) if mask is None else mask.ravel().astype(bool)


def adalam_mask(pts1: np.ndarray, pts2: np.ndarray, scores: np.ndarray, shape1: tuple[int, int],
                shape2: tuple[int, int], affine1: np.ndarray | None = None,
                affine2: np.ndarray | None = None) -> np.ndarray:
    """kornia's AdaLAM on already matched keypoints (default config; orientations and scales
    from the keypoints' frames when given)."""
    import torch
    from kornia.feature.adalam import AdalamFilter

    n = len(pts1)
    if n < 4:
        return np.zeros(n, bool)
    k1 = torch.as_tensor(np.asarray(pts1), dtype=torch.float32)
    k2 = torch.as_tensor(np.asarray(pts2), dtype=torch.float32)
    idx = torch.arange(n)
    sc = torch.as_tensor(np.asarray(scores), dtype=torch.float32)
    kwargs = {}
    if affine1 is not None and affine2 is not None:
        a1, a2 = np.asarray(affine1), np.asarray(affine2)
        kwargs = dict(
            o1=torch.as_tensor(np.degrees(np.arctan2(a1[:, 1, 0], a1[:, 0, 0])), dtype=torch.float32),
            o2=torch.as_tensor(np.degrees(np.arctan2(a2[:, 1, 0], a2[:, 0, 0])), dtype=torch.float32),
            s1=torch.as_tensor(np.sqrt(np.abs(np.linalg.det(a1))), dtype=torch.float32),
            s2=torch.as_tensor(np.sqrt(np.abs(np.linalg.det(a2))), dtype=torch.float32),
        )
    else:
        kwargs = dict(o1=torch.zeros(n), o2=torch.zeros(n), s1=torch.ones(n), s2=torch.ones(n))
    filt = AdalamFilter()  # kornia's defaults (a custom dict would replace, not update, them)
    filt.config["device"] = k1.device
    with torch.no_grad():
        out = filt.filter_matches(k1, k2, idx, sc, mnn=torch.ones(n, dtype=torch.bool),
                                  im1shape=tuple(shape1), im2shape=tuple(shape2), **kwargs)
    mask = np.zeros(n, bool)
    if out is not None and len(out):
        mask[out[:, 0].cpu().numpy()] = True
    return mask


def gms_available() -> bool:
    """GMS needs ``cv2.xfeatures2d`` (opencv-contrib), absent from opencv-python-headless."""
    import cv2

    return hasattr(cv2, "xfeatures2d") and hasattr(cv2.xfeatures2d, "matchGMS")


def gms_mask(pts1: np.ndarray, pts2: np.ndarray, shape1: tuple[int, int], shape2: tuple[int, int]) -> np.ndarray:
    """OpenCV's GMS (with rotation and scale), or RuntimeError when opencv-contrib is missing."""
    import cv2

    if not gms_available():
        raise RuntimeError("GMS needs opencv-contrib-python-headless instead of opencv-python-headless")
    kp1 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in pts1]
    kp2 = [cv2.KeyPoint(float(x), float(y), 1.0) for x, y in pts2]
    matches = [cv2.DMatch(i, i, 0.0) for i in range(len(pts1))]
    size1 = (int(shape1[1]), int(shape1[0]))
    size2 = (int(shape2[1]), int(shape2[0]))
    kept = cv2.xfeatures2d.matchGMS(size1, size2, kp1, kp2, matches, withRotation=True, withScale=True)
    mask = np.zeros(len(pts1), bool)
    mask[[m.queryIdx for m in kept]] = True
    return mask


def colmap_verification_mask(pts1: np.ndarray, pts2: np.ndarray, shape1: tuple[int, int],
                             shape2: tuple[int, int], K1: np.ndarray | None = None,
                             K2: np.ndarray | None = None) -> np.ndarray:
    """COLMAP's own two-view geometric verification (``pycolmap.estimate_two_view_geometry``,
    default options). Cameras: SIMPLE_PINHOLE from K when given, else a 1.2 * max(w, h) focal
    prior. pycolmap expects COLMAP coordinates (+0.5), converted by the database layer's
    :func:`~colmap_miho.adapters.conventions.pixel_centre_to_colmap`."""
    import pycolmap

    from colmap_miho.adapters.conventions import pixel_centre_to_colmap

    n = len(pts1)
    if n < 8:
        return np.zeros(n, bool)

    def camera(shape, K):
        h, w = shape
        if K is not None:
            f = float((K[0, 0] + K[1, 1]) / 2)
            return pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h,
                                   params=[f, *pixel_centre_to_colmap(K[:2, 2])])
        return pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h,
                               params=[1.2 * max(w, h), w / 2, h / 2, 0.0])

    matches = np.stack([np.arange(n), np.arange(n)], axis=1).astype(np.uint32)
    geom = pycolmap.estimate_two_view_geometry(
        camera(shape1, K1), pixel_centre_to_colmap(pts1),
        camera(shape2, K2), pixel_centre_to_colmap(pts2),
        matches, pycolmap.TwoViewGeometryOptions(),
    )
    mask = np.zeros(n, bool)
    inl = np.asarray(geom.inlier_matches)
    if inl.size:
        mask[inl[:, 0].astype(np.int64)] = True
    return mask


class ReferenceMiho:
    """The authors' reference MOP+MiHo / MOP (https://github.com/fb82/MiHo), run from a checkout
    of it that the user provides (nothing of it is shipped here): ``src/miho.py`` (MOP+MiHo) and
    ``src/miho_other.py`` (MOP), the modules the authors' ``run_bench.py`` calls, with their
    default parameters, on the CPU with one torch thread (like the numpy filter here). A match is
    kept when the reference assigns it a homography (``Hidx > -1``, the mask of its
    ``refinement_miho(remove_bad=True)``). The reference seeds torch itself on every call.

    Raises:
        ImportError: the checkout is missing, or lacks one of the reference's own dependencies
            (it imports PIL, OpenCV, matplotlib, torch and torchvision at module level).
    """

    def __init__(self, checkout: str) -> None:
        import importlib
        import os
        import sys

        if not os.path.isfile(os.path.join(checkout, "src", "miho.py")):
            raise ImportError(f"no src/miho.py in {checkout}: give a checkout of github.com/fb82/MiHo")
        sys.path.insert(0, os.path.abspath(checkout))
        try:
            self.modules = {"mop_miho": importlib.import_module("src.miho"),
                            "mop": importlib.import_module("src.miho_other")}
        except ImportError as exc:
            raise ImportError(f"the reference in {checkout} cannot be imported ({exc}); install its "
                              "requirements") from exc
        finally:
            sys.path.remove(os.path.abspath(checkout))

    def mask(self, method: str, pts1: np.ndarray, pts2: np.ndarray) -> np.ndarray:
        """Kept matches (N,) of the reference's ``method`` ("mop_miho" or "mop")."""
        import torch

        module = self.modules[method]
        before = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            m = module.miho()
            m.planar_clustering(torch.tensor(np.asarray(pts1), dtype=torch.float32),
                                torch.tensor(np.asarray(pts2), dtype=torch.float32))
            return (m.Hidx > -1).cpu().numpy().astype(bool)
        finally:
            torch.set_num_threads(before)
