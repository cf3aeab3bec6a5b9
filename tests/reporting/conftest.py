"""Fixtures of the reporting tests: one ``demo --quick`` run shared by the tests that read it."""

from __future__ import annotations

import pytest

from colmap_miho.cli import main


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``colmap-miho demo --quick`` into a temporary folder: ``(exit code, folder)``."""
    import logging

    out = tmp_path_factory.mktemp("demo")
    logger = logging.getLogger("colmap_miho")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    rc = main(["demo", "--quick", "--output", str(out), "-q", "--workers", "1"])
    # main() configures the package logger like an application; later tests need it as it was
    logger.handlers[:], logger.level, logger.propagate = saved
    return rc, out
