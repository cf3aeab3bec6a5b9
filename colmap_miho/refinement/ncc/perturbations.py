"""Template shape perturbations of the NCC refinement (paper Sec. 3.3, Eq. A_{rho,f}).

The paper perturbs the extended homography pair by the affine maps

    A_{rho,f} = [[f cos(rho), -f sin(rho)], [sin(rho), cos(rho)]]

with rho in {-30, -15, 0, 15, 30} degrees and f in {5/7, 5/6, 1, 6/5, 7/5} (25 shapes).
Here the perturbation is applied to the *template* only, about the template centre, so that
the search window is sampled once per match: template pixel ``w`` (common-frame offset) is
read at ``H_fixed^-1 (c + M w)`` with ``M`` one of the matrices returned below.
"""

from __future__ import annotations

import math

import numpy as np

from ...enums import Perturbations

PAPER_ROTATIONS_DEG = (-30.0, -15.0, 0.0, 15.0, 30.0)
PAPER_FACTORS = (5.0 / 7.0, 5.0 / 6.0, 1.0, 6.0 / 5.0, 7.0 / 5.0)


def shape_matrix(rho_deg: float, factor: float) -> np.ndarray:
    """The paper's ``A_{rho,f}`` (2, 2) float64: rotation by ``rho_deg`` with the first row
    scaled by ``factor`` (an anisotropic scaling / shear of the template)."""
    c, s = math.cos(math.radians(rho_deg)), math.sin(math.radians(rho_deg))
    return np.array([[factor * c, -factor * s], [s, c]], dtype=np.float64)


def perturbation_matrices(name: Perturbations | str) -> np.ndarray:
    """Template shapes of a named set as an array (K, 2, 2) float64; the identity comes first.

    - ``"none"``: only the identity (K = 1).
    - ``"small"``: identity, rotations by +-15 degrees, factors 5/6 and 6/5 (K = 5).
    - ``"paper"``: the 5 rotations x 5 factors of the paper (K = 25, identity included once).
    """
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
