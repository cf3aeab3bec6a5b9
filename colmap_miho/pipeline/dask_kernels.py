"""The compiled kernels on Dask workers: a worker plugin that fills the worker's machine's
kernel cache once (:func:`~colmap_miho.kernel_cache.ensure_compiled`: the first worker of a
machine compiles, the others wait for its lock, then find the families ready) and loads them
into the worker before its first task. The cache folder follows the same rule on every
machine (:func:`~colmap_miho.compiled.cache_dir`, from the worker's own environment).

Used only with ``--dask`` (the ``dask`` extra's ``distributed``).
"""

from __future__ import annotations

import asyncio
import importlib
import logging
from typing import TYPE_CHECKING

from ..kernel_cache import FAMILIES, ensure_compiled

try:
    from distributed.diagnostics.plugin import WorkerPlugin
except ImportError:  # without the dask extra: importable (the wheel's test imports every module), never used
    WorkerPlugin = object  # type: ignore[assignment,misc]

if TYPE_CHECKING:
    from distributed import Client

log = logging.getLogger(__name__)

#: the plugin's name on the cluster (registering it again replaces it).
PLUGIN_NAME = "colmap-miho-kernels"


class KernelCachePlugin(WorkerPlugin):
    """On each worker's start (and on registration, for the running ones): compile the
    ``families`` its machine's cache lacks, then load them. Never fails the worker: a family
    that cannot be loaded compiles in the task that uses it."""

    idempotent = False

    def __init__(self, families: tuple[str, ...]) -> None:
        self.families = tuple(families)

    async def setup(self, worker) -> None:
        # in a thread: the worker's event loop keeps answering the scheduler meanwhile
        await asyncio.get_running_loop().run_in_executor(None, self._fill_and_load)

    def _fill_and_load(self) -> None:
        ensure_compiled(self.families)
        for family in self.families:
            module, function = FAMILIES[family].warm.split(":")
            getattr(importlib.import_module(module), function)()


def load_kernels_on_workers(client: Client, families: tuple[str, ...]) -> None:
    """Register :class:`KernelCachePlugin` for ``families`` on ``client``'s cluster; returns
    once every present worker has run it (the first run on a machine compiles: tens of
    seconds)."""
    log.info("loading the compiled kernels on the Dask workers (%s)", ", ".join(families))
    client.register_plugin(KernelCachePlugin(families), name=PLUGIN_NAME)
