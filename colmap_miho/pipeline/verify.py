"""Verify stage: COLMAP's own epipolar verification of the pairs that have matches and no
two-view geometry (the write stage deleted those of the filtered pairs when ``pipeline.verify``
is on)."""

from __future__ import annotations

from pathlib import Path


def run_verify(path: Path) -> None:
    """Run ``pycolmap.geometric_verification`` on the working copy at ``path``."""
    import pycolmap

    pycolmap.geometric_verification(str(path))
