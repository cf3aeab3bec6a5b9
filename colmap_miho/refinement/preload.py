"""Imported by the worker processes' forkserver (:data:`colmap_miho.pipeline.workers.PRELOAD`):
loads the compiled NCC kernels (:func:`.ncc_kernel.warm`), the local affine fits
(:func:`.affine_kernel.warm`) and the LSM step (:func:`.lsm_kernel.warm`) once in the
forkserver, so that every worker forked from it starts with them instead of loading them itself."""

from __future__ import annotations

from . import affine_kernel, lsm_kernel
from .ncc_kernel import warm

warm()
affine_kernel.warm()
lsm_kernel.warm()
