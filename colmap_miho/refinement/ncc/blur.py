"""Blur matching: the sharper image of a pair smoothed to the blur of the other before NCC.

Two photos of one scene rarely carry the same blur: focus, motion, a zoom, a smaller aperture.
The correlation of a sharp patch with a blurred one has a broad, low peak that image noise
moves: on a pair whose second image is strongly defocused, NCC places keypoints farther from
the truth than SIFT did. Smoothing the sharper image with the Gaussian that makes both
carry the same blur restores a peak that is as sharp as the blurred image allows, at the
true position (a symmetric blur does not move it).

The blur to add is estimated from the pair's own matches, without ground truth: the patches
of up to ``max_matches`` matches (evenly spread over the input order) are read rectified in
each match's common frame (the first homography pair: MOP's plane, MiHo's midpoint frame),
each side is smoothed by every candidate Gaussian of :data:`BLUR_LEVELS_PX`, and the (side,
sigma) whose median NCC over the matches is highest wins, when it beats the unsmoothed
median, the same Gaussian on the other side lowers it, and the matches agree: a one-sided
sign test that smoothing this side beats smoothing the other, match by match, at
:data:`SIGN_TEST_P` over all candidates. A real blur difference does all three; keypoints
that are still off by a pixel, a 3-D scene that the local homographies fit only roughly, or
noise make smoothing either side raise the NCC of some matches and lower it for others, and
such a pair, like one with too few matches to tell, is left as it is. The NCC is the
quantity the search itself maximises. The chosen sigma (common-frame pixels) is converted to the smoothed
image's own pixels with the median local scale of its frame -> image maps, and the whole
image is smoothed once (separable Gaussian, ``kornia.filters.gaussian_blur2d``) before the
refinement reads it; the other image is read as it is.

With an :class:`~..warping.ImageStack` (several image pairs in one call), each distinct pair of
images is estimated on its own matches, and a smoothed copy of the chosen image is added to
the stack for those matches only, so a match's result still depends on its own pair alone.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from ...geometry import spread_rows
from ..lsm.align import frame_sampler
from ..warping import ImageStack, frame_jacobian, job_images, local_scale, to_frame

logger = logging.getLogger(__name__)

#: candidate Gaussians (standard deviation, common-frame pixels) added to one side: a search
#: grid from one pixel to the blur at which a 10-pixel template keeps little texture. Below
#: one pixel, smoothing either side of an equally sharp pair raises the median NCC a little
#: by averaging noise (by 0.001-0.01 on Oxford pairs without a blur change), and the
#: keypoints it then places are less accurate, so half a pixel is not a candidate.
BLUR_LEVELS_PX = (1.0, 1.5, 2.0, 3.0, 4.0)
#: radius (pixels) of the patches compared by the estimate.
PATCH_RADIUS = 8
#: significance of the sign test that a blur difference must pass (over all candidates).
SIGN_TEST_P = 1e-3
#: matches of one image pair read by the estimate at most (evenly spread over the input).
MAX_MATCHES = 256


@dataclass(frozen=True)
class BlurChoice:
    """Outcome of :func:`estimate_blur` for one image pair: ``side`` 0 (neither smoothed), 1
    or 2 (that image is smoothed), ``sigma_px`` the Gaussian in that image's own pixels (0 for
    side 0), ``ncc`` the median NCC of the compared patches before and with the choice."""

    side: int
    sigma_px: float
    ncc: tuple[float, float]


def _ncc(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """NCC of patches ``a`` and ``b`` (..., n, s, s) -> (..., n)."""
    a = a - a.mean(dim=(-2, -1), keepdim=True)
    b = b - b.mean(dim=(-2, -1), keepdim=True)
    den = (a.square().sum(dim=(-2, -1)) * b.square().sum(dim=(-2, -1))).sqrt().clamp_min(1e-12)
    return (a * b).sum(dim=(-2, -1)) / den


def estimate_blur(
    image1: torch.Tensor | ImageStack,
    image2: torch.Tensor | ImageStack,
    frame1: torch.Tensor,
    frame2: torch.Tensor,
    H1_inv: torch.Tensor,
    H2_inv: torch.Tensor,
) -> BlurChoice:
    """The Gaussian to add to one image of a pair so that its matched patches correlate best.

    Args:
        image1, image2: (H, W) float32 images, or :class:`~..warping.ImageStack` objects
            with one image per match (all matches of one image pair).
        frame1, frame2: (n, 2) float64 common-frame positions of the keypoints.
        H1_inv, H2_inv: (n, 3, 3) float64 common frame -> image pixels of each side.
    """
    n = frame1.shape[0]
    if n == 0:
        return BlurChoice(0, 0.0, (float("nan"), float("nan")))
    # imported here: they take seconds to import, and only this option needs them
    from kornia.filters import get_gaussian_kernel1d
    from scipy.stats import binom

    margin = int(np.ceil(3 * max(BLUR_LEVELS_PX)))
    big = PATCH_RADIUS + margin
    rows = torch.arange(n, device=frame1.device)
    eye = torch.eye(2, dtype=torch.float64, device=frame1.device).expand(n, 2, 2)
    zero = torch.zeros((n, 2), dtype=torch.float64, device=frame1.device)
    patches = [frame_sampler(im, Hi, fr)(rows, eye, zero, big)
               for im, Hi, fr in ((image1, H1_inv, frame1), (image2, H2_inv, frame2))]
    centre = slice(margin, margin + 2 * PATCH_RADIUS + 1)
    plain = [p[:, centre, centre] for p in patches]
    sigmas = torch.tensor(BLUR_LEVELS_PX, dtype=torch.float32, device=frame1.device)[:, None]
    kernels = get_gaussian_kernel1d(2 * margin + 1, sigmas, device=frame1.device)  # (L, 2m+1)
    base_each = _ncc(plain[0], plain[1])  # (n,)
    base = float(base_each.median())
    each = [_ncc(sm, plain[1 - side].expand_as(sm))  # 2 x (L, n)
            for side, sm in enumerate(_smooth(p, kernels) for p in patches)]
    scores = [e.median(dim=1).values.tolist() for e in each]
    level = SIGN_TEST_P / (2 * len(BLUR_LEVELS_PX))  # Bonferroni over the candidates
    best = (base, 0, 0.0)
    for side in (0, 1):
        for k, sigma in enumerate(BLUR_LEVELS_PX):
            # a blur difference raises the NCC when the sharper side is smoothed and lowers it
            # when the other one is; misaligned or noisy patches gain either way
            if not (scores[side][k] > best[0] and scores[1 - side][k] < base):
                continue
            wins = int((each[side][k] > each[1 - side][k]).sum())
            if binom.sf(wins - 1, n, 0.5) < level:  # one-sided sign test
                best = (scores[side][k], side + 1, sigma)
    score, side, sigma = best
    if side == 0:
        return BlurChoice(0, 0.0, (base, base))
    H_inv, frame = (H1_inv, frame1) if side == 1 else (H2_inv, frame2)
    scale = float(local_scale(frame_jacobian(H_inv, frame)).median())
    return BlurChoice(side, sigma * scale, (base, score))


def _smooth(patches: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
    """(L, n, S - 2 margin, S - 2 margin): the (n, S, S) patches smoothed by each of the L
    separable Gaussians ``kernels`` (L, 2 margin + 1), valid part only."""
    L, width = kernels.shape
    n, S, _ = patches.shape
    x = patches[:, None].expand(n, L, S, S)
    rows = torch.nn.functional.conv2d(x, kernels[:, None, :, None], groups=L)  # (n, L, S-2m, S)
    both = torch.nn.functional.conv2d(rows, kernels[:, None, None, :], groups=L)  # (n, L, s, s)
    return both.permute(1, 0, 2, 3)


def smoothed(image: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """(H, W) float32 ``image`` smoothed by a Gaussian of ``sigma_px`` pixels (kernel of
    2 ceil(3 sigma) + 1 taps, borders reflected)."""
    from kornia.filters import gaussian_blur2d

    half = int(np.ceil(3 * sigma_px))
    size = 2 * half + 1
    return gaussian_blur2d(image[None, None], (size, size), (sigma_px, sigma_px),
                           border_type="reflect")[0, 0]


def _frames(p: np.ndarray, H: np.ndarray, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Common-frame positions (n, 2) of the pixels ``p`` (n, 2) under ``H`` (n, 3, 3) (image
    -> frame), and the inverse maps (n, 3, 3), float64 on ``device``."""
    Ht = torch.as_tensor(H, dtype=torch.float64, device=device)
    return to_frame(Ht, torch.as_tensor(p, dtype=torch.float64, device=device)), torch.linalg.inv(Ht)


def _sample_rows(n: int) -> np.ndarray:
    """At most :data:`MAX_MATCHES` row indices evenly spread over ``n`` rows."""
    return spread_rows(n, MAX_MATCHES)


def match_blur(
    images: tuple[torch.Tensor | ImageStack, torch.Tensor | ImageStack],
    p1: np.ndarray,
    p2: np.ndarray,
    homs: np.ndarray,
) -> tuple[tuple[torch.Tensor | ImageStack, torch.Tensor | ImageStack], dict[str, int]]:
    """The images of a refine call with the sharper image of each image pair smoothed
    (:func:`estimate_blur` on that pair's matches), and counters.

    Args:
        images: (image 1, image 2) as :func:`~..pairwise.refine_pair` holds them: (H, W) float32
            tensors, or :class:`~..warping.ImageStack` objects with one image per match.
        p1, p2: (N, 2) float64 keypoints.
        homs: (N, 2, 3, 3) float64 first patch homography pair of each match.
    Returns:
        (the two images, smoothed where chosen; ``blur_pairs`` image pairs and
        ``blur_matched`` matches whose one image was smoothed).
    """
    counts = {"blur_pairs": 0, "blur_matched": 0}
    n = p1.shape[0]
    if n == 0:
        return images, counts
    im1, im2 = images
    device = (im1.images[0] if isinstance(im1, ImageStack) else im1).device
    keys = [im.index.cpu().numpy() if isinstance(im, ImageStack) else np.zeros(n, np.int64)
            for im in (im1, im2)]
    pair_of = keys[0] * (int(keys[1].max()) + 1) + keys[1]
    new_images: list[list[torch.Tensor]] = [[], []]
    new_index = [k.copy() for k in keys]
    plain = [None if isinstance(im, ImageStack) else im for im in (im1, im2)]
    for key in np.unique(pair_of):
        members = np.flatnonzero(pair_of == key)
        sub = members[_sample_rows(members.size)]
        f1, H1_inv = _frames(p1[sub], homs[sub, 0], device)
        f2, H2_inv = _frames(p2[sub], homs[sub, 1], device)
        pick = torch.as_tensor(sub, device=device)
        views = [job_images(im, pick) for im in (im1, im2)]
        choice = estimate_blur(views[0], views[1], f1, f2, H1_inv, H2_inv)
        logger.debug("blur matching: %d matches, %s", members.size, choice)
        if choice.side == 0:
            continue
        s = choice.side - 1
        im = images[s]
        source = im.images[int(keys[s][members[0]])] if isinstance(im, ImageStack) else im
        blurred = smoothed(source, choice.sigma_px)
        if isinstance(im, ImageStack):
            new_index[s][members] = len(im.images) + len(new_images[s])
            new_images[s].append(blurred)
        else:
            plain[s] = blurred
        counts["blur_pairs"] += 1
        counts["blur_matched"] += int(members.size)
    out: list[torch.Tensor | ImageStack] = []
    for s, im in enumerate((im1, im2)):
        if isinstance(im, ImageStack):
            out.append(ImageStack.build(list(im.images) + new_images[s], new_index[s], device)
                       if new_images[s] else im)
        else:
            kept = plain[s]
            out.append(im if kept is None else kept)
    return (out[0], out[1]), counts
