"""The ``refine`` pipeline: read -> filter -> refine -> write -> verify, on a working copy.

:func:`refine_database` (in :mod:`.refine`) runs the stages in the order of the data flow, one
``run_<stage>`` call each: :mod:`.read`, :mod:`.filter_stage`, :mod:`.stages` (the NCC
refinement), :mod:`.write`, :mod:`.verify`; :mod:`.workers` holds the process-pool helpers;
:class:`PipelineConfig` is the recipe's ``pipeline`` table.
"""

from .config import PipelineConfig
from .refine import RefineSummary, refine_database

__all__ = ["PipelineConfig", "RefineSummary", "refine_database"]
