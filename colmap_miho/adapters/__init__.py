"""Input/output adapters: COLMAP databases and cameras, images, hloc h5 files, file safety and paths.

Only :mod:`colmap_miho.adapters.database` (with :mod:`~colmap_miho.adapters.database_build`, the
base class that fills new databases) reads and writes COLMAP databases, and it is the only place
where the half-pixel shift between colmap-miho's convention (integer = pixel centre, OpenCV) and
COLMAP's (pixel (0, 0) covers [0, 1) x [0, 1)) is applied.
"""
