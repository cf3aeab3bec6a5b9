"""NCC keypoint refinement: pairwise engine and track-consistent walk (paper Sec. 3.3, App. E)."""
