"""What one least-squares alignment returns and the bounds it is judged by (torch and compiled paths)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

#: Gauss-Newton stops for a match once its shift update is below this (common-frame pixels).
DEFAULT_TOL_PX = 1e-3
#: singular values of A outside [1 / MAX_SCALE, MAX_SCALE] mark a degenerate alignment.
MAX_SCALE = 2.0
#: gains r1 outside [1 / MAX_GAIN, MAX_GAIN] mark a degenerate alignment.
MAX_GAIN = 5.0


@dataclass(frozen=True)
class LSMResult:
    """Output of :func:`.align.lsm_align` and :func:`.kernel.lsm_frames` for J matches (common-frame
    pixels): final ``shift`` ``(J, 2)`` and its ``sigma``, ``sigma_max`` (the error ellipse's
    largest semi-axis, +inf when singular), ``affine``, ``gain``, ``offset``, ``residual_std``,
    ``converged`` and ``iterations``."""

    shift: torch.Tensor
    sigma: torch.Tensor
    sigma_max: torch.Tensor
    affine: torch.Tensor
    gain: torch.Tensor
    offset: torch.Tensor
    residual_std: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
