"""Template shape perturbations of the NCC refinement (paper Sec. 3.3): ``A_{rho,f} = [[f cos rho,
-f sin rho], [sin rho, cos rho]]``, applied to the template only, so the window is sampled once."""

from __future__ import annotations

import math

import numpy as np

from ...enums import Perturbations

PAPER_ROTATIONS_DEG = (-30.0, -15.0, 0.0, 15.0, 30.0)
PAPER_FACTORS = (5.0 / 7.0, 5.0 / 6.0, 1.0, 6.0 / 5.0, 7.0 / 5.0)


def shape_matrix(rho_deg: float, factor: float) -> np.ndarray:
    """The paper's ``A_{rho,f}`` ``(2, 2)``: rotation by ``rho_deg``, first row scaled by ``factor``."""
    c, s = math.cos(math.radians(rho_deg)), math.sin(math.radians(rho_deg))
    return np.array([[factor * c, -factor * s], [s, c]], dtype=np.float64)


def perturbation_matrices(name: Perturbations | str) -> np.ndarray:
    """Template shapes ``(K, 2, 2)`` of a named set, identity first: ``"none"`` (1), ``"small"`` (5:
    +-15 degrees, 5/6 and 6/5) or ``"paper"`` (25)."""
    name = Perturbations.parse(name, "perturbations")
    if name is Perturbations.NONE:
        return np.eye(2)[None].copy()
    if name is Perturbations.SMALL:
        shapes = [(0.0, 1.0), (-15.0, 1.0), (15.0, 1.0), (0.0, 5.0 / 6.0), (0.0, 6.0 / 5.0)]
    else:  # PAPER
        shapes = [(0.0, 1.0)] + [
            (r, f) for r in PAPER_ROTATIONS_DEG for f in PAPER_FACTORS if (r, f) != (0.0, 1.0)
        ]
    return np.stack([shape_matrix(r, f) for r, f in shapes])
