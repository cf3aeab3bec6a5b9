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


def pytest_collection_modifyitems(config, items):
    """Every test that uses the ``shared_data`` fixture (directly or through another fixture)
    reads ``../shared/data``: mark it ``realdata`` so that ``-m realdata`` / ``-m "not realdata"``
    select exactly the real-data suite or the offline one."""
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.realdata)


def pytest_configure(config):
    """The signal tests send Ctrl-C, SIGTERM and SIGHUP as a terminal would. A shell starts its
    background jobs with SIGINT ignored, and colmap-miho keeps a signal ignored at start (as
    ``nohup`` needs): give this process, and so the commands it starts, the signals' defaults."""
    import signal

    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is not None and signal.getsignal(sig) == signal.SIG_IGN:
            signal.signal(sig, signal.SIG_DFL)


@pytest.fixture(autouse=True)
def _restore_package_logger():
    """``cli.main`` configures the ``colmap_miho`` logger like an application does (own handler,
    no propagation); every test starts with the library's own logger (a module-scoped fixture
    that ran ``main`` would otherwise leave that behind), so that caplog sees log records."""
    import logging

    logger = logging.getLogger("colmap_miho")
    logger.handlers[:] = [h for h in logger.handlers if isinstance(h, logging.NullHandler)]
    logger.setLevel(logging.NOTSET)
    logger.propagate = True
    yield
