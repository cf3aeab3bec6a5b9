"""Imported by the worker processes' forkserver (:data:`colmap_miho.pipeline.workers.PRELOAD`):
loads the compiled filter kernels (:func:`.kernels.warm`) once in the forkserver, so that
every worker forked from it starts with them instead of loading them itself."""

from __future__ import annotations

from .kernels import warm

warm()
