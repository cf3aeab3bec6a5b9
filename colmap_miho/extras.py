"""Optional dependencies (the pyproject extras ``demo``, ``plots``, ``pointcloud``, ``dask``):
import one, or fail with one line naming the extra."""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import UserError

PACKAGE_OF = {"matplotlib": "matplotlib", "skimage": "scikit-image", "open3d": "open3d", "distributed": "distributed"}


class MissingExtraError(UserError):
    """An optional dependency is not installed; the message says which extra to install."""


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import and return ``module`` of extra ``extra``, or raise MissingExtraError naming
    ``purpose`` and the install command."""
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        package = PACKAGE_OF.get(top, top)
        raise MissingExtraError(
            f"{purpose} needs {package}, which is not installed: pip install 'colmap-miho[{extra}]'"
        ) from None
