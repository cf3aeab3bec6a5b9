"""What a user reads after mapping: reports, ground-truth models, plots, the comparison and the demo
scene (no torch; pycolmap and matplotlib imported where needed)."""
