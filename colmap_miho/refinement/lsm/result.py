"""What one least-squares alignment returns, and the bounds it is judged by: shared by the
torch alignment (:mod:`.align`, the reference) and its compiled kernel (:mod:`.kernel`)."""

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
    """Output of :func:`.align.lsm_align` and :func:`.kernel.lsm_frames` (J matches; common-frame pixels).

    Attributes:
        shift: (J, 2) float64 final shift t (x, y) relative to each match's centre.
        sigma: (J, 2) float64 a-posteriori standard deviations of t's x and y.
        sigma_max: (J,) float64 largest semi-axis of t's standard error ellipse (the
            precision along the least determined direction); +inf where the normal matrix
            is singular.
        affine: (J, 2, 2) float64 final A.
        gain, offset: (J,) float64 final r1, r0.
        residual_std: (J,) float64 s0 (intensity units of the inputs).
        converged: (J,) bool: the shift update fell below the tolerance within the
            iterations allowed, and A, the gain and the normal matrix stayed regular.
        iterations: (J,) int64 Gauss-Newton steps taken.
    """

    shift: torch.Tensor
    sigma: torch.Tensor
    sigma_max: torch.Tensor
    affine: torch.Tensor
    gain: torch.Tensor
    offset: torch.Tensor
    residual_std: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
