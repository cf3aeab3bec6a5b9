"""What a user reads after mapping: reconstruction reports (pose AUC, model statistics, point
clouds), ground-truth models, plots, the with/without comparison and the built-in demo scene.

Imports torch nowhere; pycolmap and matplotlib only inside the functions that need them.
"""
