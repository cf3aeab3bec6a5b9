"""Every pycolmap call that extracts, matches or maps: COLMAP's extraction and matching
(:mod:`.extraction`), incremental and global mapping (:mod:`.mapping`), the global estimate
of the cameras that the match check judges against (:mod:`.global_estimate`), and COLMAP's log
sent to a file (:mod:`.colmap_log`)."""

from .colmap_log import colmap_log_to_file
from .mapping import MappingConfig, MappingResult, RefineIntrinsics, parse_camera_params, require_success, run_mapping

__all__ = ["MappingConfig", "MappingResult", "RefineIntrinsics", "colmap_log_to_file", "parse_camera_params",
           "require_success", "run_mapping"]
