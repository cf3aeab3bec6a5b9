"""The compiled kernels on Dask workers: a plugin that fills each machine's kernel cache once (the
first worker compiles, the others wait on its lock) and loads it before the first task."""

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
    """On each worker's start: compile the ``families`` its cache lacks, then load them; never fails."""

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
    """Register :class:`KernelCachePlugin` on ``client``'s cluster; returns once every worker ran it."""
    log.info("loading the compiled kernels on the Dask workers (%s)", ", ".join(families))
    client.register_plugin(KernelCachePlugin(families), name=PLUGIN_NAME)
