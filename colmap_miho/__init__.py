"""colmap-miho: MOP+MiHo match filtering and track-consistent NCC refinement for COLMAP.

Public API (imported lazily so that the CLI starts without torch)::

    filter_matches(pts1, pts2, *, method="mop_miho", config=None, seed=0) -> FilterResult
    refine_pair(image1, image2, pts1, pts2, patch_homographies, *, move="auto", config=None)
        -> RefineResult
    refine_tracks(images, keypoints, pair_matches, pair_filter_results, *, config=None)
        -> TrackRefineResult
    load_recipe(name_or_path=None, overrides=None) -> Recipe

Pixel convention everywhere in the API: (x, y), integer = pixel centre (OpenCV). The +0.5
shift to COLMAP's convention happens only in ``colmap_miho.adapters.database``.
"""

from __future__ import annotations

import importlib
import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

_LAZY = {
    "filter_matches": "colmap_miho.filtering.api",
    "FilterResult": "colmap_miho.filtering.api",
    "FilterConfig": "colmap_miho.filtering.config",
    "refine_pair": "colmap_miho.refinement.ncc",
    "RefineResult": "colmap_miho.refinement.ncc",
    "refine_tracks": "colmap_miho.refinement.tracks",
    "TrackRefineResult": "colmap_miho.refinement.tracks",
    "NCCConfig": "colmap_miho.refinement.config",
    "TrackConfig": "colmap_miho.refinement.config",
    "load_recipe": "colmap_miho.recipe",
    "Recipe": "colmap_miho.recipe",
    "FilterMethod": "colmap_miho.enums",
    "MoveSide": "colmap_miho.enums",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'colmap_miho' has no attribute {name!r}")


def __dir__():
    return __all__
