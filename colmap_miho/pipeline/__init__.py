"""The ``refine`` pipeline: read -> filter -> match check -> refine keypoints -> write ->
re-verify, on a working copy, and the whole jobs built on it.

:func:`refine_database` (:mod:`.refine_job`) calls the stages in the order of the data flow, one
``run_<stage>`` call each, every one returning its outputs and frozen stats: :mod:`.read`,
:mod:`.filter`, :mod:`.match_check_stage` (the global estimate's
verdicts, on by default), :mod:`.refine_keypoints` (the NCC walk), :mod:`.write`, :mod:`.reverify`
(COLMAP's re-verification, off by default).
:mod:`.records` holds what passes between stages, :mod:`.summary` the run's
:class:`RefineSummary`, :mod:`.store` the resumable run store (:mod:`.store_checks` what its
files read back must be), :mod:`.executor` and :mod:`.workers` the process pool and Dask
runners, :mod:`.jobs` the whole jobs of ``run``, ``compare`` and ``demo`` (extraction,
refinement, mapping, comparison).
"""

from ..pipeline_config import PipelineConfig
from .refine_job import refine_database
from .summary import RefineSummary

__all__ = ["PipelineConfig", "RefineSummary", "refine_database"]
