"""The ``refine`` pipeline: read -> filter -> refine -> write -> verify, on a working copy.

:func:`refine_database` (in :mod:`.refine`) runs the stages in the order of the data flow; the
heavy stages and their worker processes are in :mod:`.stages`; :class:`PipelineConfig` is the
recipe's ``pipeline`` table.
"""

from .config import PipelineConfig
from .refine import RefineSummary, refine_database

__all__ = ["PipelineConfig", "RefineSummary", "refine_database"]
