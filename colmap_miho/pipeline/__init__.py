"""The ``refine`` pipeline: read -> filter -> pair check -> match check -> refine -> write ->
verify, on a working copy (:func:`refine_database`, one ``run_<stage>`` call each), and the whole
jobs built on it (:mod:`.jobs`)."""

from ..pipeline_config import PipelineConfig
from .run import refine_database
from .summary import RefineSummary

__all__ = ["PipelineConfig", "RefineSummary", "refine_database"]
