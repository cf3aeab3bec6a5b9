"""Imported by the worker processes' forkserver (:data:`colmap_miho.pipeline.workers.PRELOAD`):
loads the compiled NCC kernels (:func:`.ncc_kernel.warm`) once in the forkserver, so that
every worker forked from it starts with them instead of loading them itself."""

from __future__ import annotations

from .ncc_kernel import warm

warm()
