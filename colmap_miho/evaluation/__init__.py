"""Evaluation: real-data loaders, matching front ends, GT match errors, pose metrics, reports."""
