"""Re-verification stage: COLMAP's own geometric verification of the pairs left without a two-view geometry."""

from __future__ import annotations

from pathlib import Path


def run_reverify(path: Path) -> None:
    """Run ``pycolmap.geometric_verification`` on the working copy at ``path``."""
    import pycolmap

    pycolmap.geometric_verification(str(path))
