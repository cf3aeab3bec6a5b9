"""Shared fixtures: the real data folder ``../shared/data`` (tests skip when it is absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data``."""
    env = os.environ.get("COLMAP_MIHO_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = shared_data_dir()
    if not (root / "README.md").is_file():
        pytest.skip(f"real data folder not found at {root} (set COLMAP_MIHO_DATA or place ../shared/data)")
    return root
