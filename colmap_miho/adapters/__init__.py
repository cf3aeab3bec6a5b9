"""Input/output adapters: COLMAP databases and cameras, images, hloc h5 files, file safety and
paths. Only :mod:`.database` touches COLMAP databases and applies the half-pixel shift."""
