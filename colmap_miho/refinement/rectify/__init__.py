"""Local affine rectification: a patch homography pair per match from its nearest matches."""
