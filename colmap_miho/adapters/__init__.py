"""Input/output adapters: COLMAP databases, images, file safety and synthetic scenes.

Only :mod:`colmap_miho.adapters.database` touches COLMAP databases, and it is the only place where
the half-pixel shift between colmap-miho's convention (integer = pixel centre, OpenCV) and
COLMAP's (pixel (0, 0) covers [0, 1) x [0, 1)) is applied.
"""
