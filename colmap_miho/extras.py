"""Optional dependencies (the pyproject extras): import one, or fail with one line naming the extra.

Extras: ``demo`` (scikit-image for the demo scene's textures, matplotlib for its plots),
``plots`` (matplotlib: compare's figures, point-cloud pictures without open3d; plotly:
``report.html``; the ``demo`` extra includes it),
``pointcloud`` (open3d, see :mod:`colmap_miho.reporting.pointcloud`), ``dask`` (Dask's
``distributed``: ``refine --dask``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import UserError

PACKAGE_OF = {"matplotlib": "matplotlib", "skimage": "scikit-image", "open3d": "open3d", "distributed": "distributed"}


class MissingExtraError(UserError):
    """An optional dependency is not installed; the message says which extra to install."""


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import and return ``module`` (e.g. ``"skimage.data"``), part of pyproject extra ``extra``.

    Raises:
        MissingExtraError: the module cannot be imported; the one-line message names what
            needs it (``purpose``) and the command that installs it.
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        package = PACKAGE_OF.get(top, top)
        raise MissingExtraError(
            f"{purpose} needs {package}, which is not installed: pip install 'colmap-miho[{extra}]'"
        ) from None
