"""Track-consistent refinement: the track plan (data) and its builder, the walk, the walk's
refine calls, and the joint multi-photo LSM after it."""
