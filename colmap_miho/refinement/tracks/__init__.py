"""Track-consistent refinement: the track plan, the walk and the joint multi-photo LSM."""
