"""colmap-miho: MOP+MiHo match filtering and track-consistent NCC + least-squares refinement for COLMAP.

Public API (imported on first use, so that ``colmap-miho --help`` starts without torch)::

    refine_database(database, image_dir, output=None, *, recipe=None, ...) -> RefineSummary
    extract_and_match(image_dir, database, ...); run_mapping(database, image_dir, output, ...)
    build_report(...); compare_databases(database, image_dir, output, *, recipe=None, gt=None, ...)
    filter_matches(pts1, pts2, *, method=None, config=None, seed=0, device="cpu") -> FilterResult
        (method None: config.method, or "mop_miho" without a config)
    refine_pair(image1, image2, pts1, pts2, patch_homographies, *, move=None, config=None)
        -> RefineResult   (move None: config.move, "auto" by default)
    refine_tracks(images, keypoints, pair_matches, pair_filter_results, *, config=None)
        -> TrackRefineResult
    load_recipe(name_or_path=None, overrides=None) -> Recipe   (None: mop_miho_lsm, the default)

Pixel convention everywhere in the API: (x, y), integer = pixel centre (OpenCV). The +0.5
shift to COLMAP's convention happens only in ``colmap_miho.adapters.database``."""

from __future__ import annotations

import importlib
import logging
from typing import TYPE_CHECKING

from .version import __version__

logging.getLogger(__name__).addHandler(logging.NullHandler())

if TYPE_CHECKING:  # what static tools see; at run time the table below imports on first use
    from .enums import FilterMethod, MoveSide
    from .filtering.api import FilterResult, filter_matches
    from .filtering.config import FilterConfig
    from .pipeline import PipelineConfig, RefineSummary, refine_database
    from .pipeline.jobs import ExtractionOptions, JobOptions, compare_databases
    from .recipe import Recipe, load_recipe
    from .refinement.config import LSMConfig, NCCConfig, RectifyConfig, TrackConfig
    from .refinement.pairwise import RefineResult, refine_pair
    from .refinement.tracks.walk import TrackRefineResult, refine_tracks
    from .reporting.report import build_report
    from .sfm import MappingResult, run_mapping
    from .sfm.extraction import extract_and_match

_LAZY = {
    "filter_matches": "colmap_miho.filtering.api",
    "FilterResult": "colmap_miho.filtering.api",
    "FilterConfig": "colmap_miho.filtering.config",
    "refine_pair": "colmap_miho.refinement.pairwise",
    "RefineResult": "colmap_miho.refinement.pairwise",
    "refine_tracks": "colmap_miho.refinement.tracks.walk",
    "TrackRefineResult": "colmap_miho.refinement.tracks.walk",
    "LSMConfig": "colmap_miho.refinement.config",
    "NCCConfig": "colmap_miho.refinement.config",
    "RectifyConfig": "colmap_miho.refinement.config",
    "TrackConfig": "colmap_miho.refinement.config",
    "load_recipe": "colmap_miho.recipe",
    "Recipe": "colmap_miho.recipe",
    "FilterMethod": "colmap_miho.enums",
    "MoveSide": "colmap_miho.enums",
    "refine_database": "colmap_miho.pipeline",
    "RefineSummary": "colmap_miho.pipeline",
    "PipelineConfig": "colmap_miho.pipeline",
    "extract_and_match": "colmap_miho.sfm.extraction",
    "run_mapping": "colmap_miho.sfm",
    "MappingResult": "colmap_miho.sfm",
    "build_report": "colmap_miho.reporting.report",
    "compare_databases": "colmap_miho.pipeline.jobs",
    "JobOptions": "colmap_miho.pipeline.jobs",
    "ExtractionOptions": "colmap_miho.pipeline.jobs",
}

__all__ = [
    "ExtractionOptions",
    "FilterConfig",
    "FilterMethod",
    "FilterResult",
    "JobOptions",
    "LSMConfig",
    "MappingResult",
    "MoveSide",
    "NCCConfig",
    "PipelineConfig",
    "Recipe",
    "RectifyConfig",
    "RefineResult",
    "RefineSummary",
    "TrackConfig",
    "TrackRefineResult",
    "__version__",
    "build_report",
    "compare_databases",
    "extract_and_match",
    "filter_matches",
    "load_recipe",
    "refine_database",
    "refine_pair",
    "refine_tracks",
    "run_mapping",
]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # resolve once
        return value
    raise AttributeError(f"module 'colmap_miho' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
