"""Worker processes of the pipeline: a ``spawn`` pool with one BLAS/torch thread per process,
and per-pair seeds that do not depend on the worker count or order.

Measured on the 2-core machine: one torch thread is 4x faster than two for the NCC walk, and
threads over track chunks were slower than one thread (the walk holds the GIL), hence processes.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

_SINGLE_THREAD_ENV = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def pair_seed(seed: int, image_id1: int, image_id2: int) -> int:
    """Seed of one pair, independent of worker count and order."""
    return int(np.random.SeedSequence([int(seed), int(image_id1), int(image_id2)]).generate_state(1)[0])


def init_worker() -> None:
    """One torch thread per worker process (the parallelism is across pairs)."""
    if "torch" in sys.modules:  # the filter is numpy; only pay for torch if it is loaded
        sys.modules["torch"].set_num_threads(1)


@contextlib.contextmanager
def single_thread_children():
    """Spawned workers inherit the environment: make their BLAS/OpenMP single-threaded."""
    saved = {k: os.environ.get(k) for k in _SINGLE_THREAD_ENV}
    os.environ.update(_SINGLE_THREAD_ENV)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def process_pool(workers: int, **kwargs):
    """A spawn process pool whose queued work is cancelled, not waited for, when the block
    raises (a failed worker, Ctrl-C)."""
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             **kwargs) as ex:
        try:
            yield ex
        except BaseException:
            ex.shutdown(wait=False, cancel_futures=True)
            raise
