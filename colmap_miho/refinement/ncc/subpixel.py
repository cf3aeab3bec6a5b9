"""Iterated sub-pixel refinement of an NCC peak: a parabola on the integer NCC map is biased towards
integers ("pixel locking"); re-sampling at the estimate and fitting again removes most of it. On CPU
tensors the compiled :func:`.kernel.subpixel` runs; this is its reference."""

from __future__ import annotations

import torch

from ..warping import ImageStack, job_images, offset_grid, sample_values
from . import kernel
from .correlation import ncc_maps, normalize_templates, parabola_vertex

#: an iteration that moves a match by less than this (common-frame pixels) ends its refinement.
_CONVERGED_PX = 1e-3


def iterate_subpixel(
    image: torch.Tensor | ImageStack,
    H_inv: torch.Tensor,
    centres: torch.Tensor,
    offset: torch.Tensor,
    templates: torch.Tensor,
    template_radius: int,
    iterations: int,
    compiled: bool | None = None,
) -> torch.Tensor:
    """Refine sub-pixel offsets ``(n, 2)`` of the ``templates`` in the moving image.

    ``H_inv`` ``(n, 3, 3)`` common frame -> image pixels, ``centres`` ``(n, 2)``, ``offset`` the
    current estimate; ``iterations`` re-centred fits (0: unchanged). Each match stops on its own
    once a step is below 1e-3 px."""
    if iterations <= 0 or offset.shape[0] == 0:
        return offset
    if compiled is None:
        compiled = offset.device.type == "cpu"
    if compiled:
        return kernel.subpixel(image, H_inv, centres, offset, templates, template_radius, iterations)
    ring = offset_grid(template_radius + 1, offset.device)[None]
    side = 2 * template_radius + 3
    rows = torch.arange(offset.shape[0], device=offset.device)  # the matches still moving
    tpl = normalize_templates(templates[:, None])
    offset = offset.clone()
    for _ in range(iterations):
        img = job_images(image, rows)
        win, _ = sample_values(img, H_inv[rows], centres[rows] + offset[rows], ring)
        m3 = ncc_maps(win.reshape(-1, side, side), tpl[rows], normalized=True)[:, 0]
        m3 = m3.to(torch.float64)
        c0 = m3[:, 1, 1]
        step = torch.stack(
            [parabola_vertex(c0, m3[:, 1, 0], m3[:, 1, 2]), parabola_vertex(c0, m3[:, 0, 1], m3[:, 2, 1])], -1
        )
        offset[rows] = offset[rows] + step
        # a converged match is left out of the next iterations (its result does not
        # depend on the others: sampling and NCC are per match)
        rows = rows[step.abs().amax(dim=1) >= _CONVERGED_PX]
        if rows.numel() == 0:
            break
    return offset
