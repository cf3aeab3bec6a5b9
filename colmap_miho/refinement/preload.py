"""Imported by the worker processes' forkserver (:data:`colmap_miho.pipeline.workers.PRELOAD`):
loads the compiled NCC kernels (:func:`.ncc.kernel.warm`), the local affine fits
(:func:`.rectify.kernel.warm`) and the LSM step (:func:`.lsm.kernel.warm`) once in the
forkserver, so that every worker forked from it starts with them instead of loading them itself."""

from __future__ import annotations

from .lsm import kernel as lsm_kernel
from .ncc import kernel as ncc_kernel
from .rectify import kernel as affine_kernel

ncc_kernel.warm()
affine_kernel.warm()
lsm_kernel.warm()
