"""Imported by the worker processes' forkserver (:data:`colmap_miho.pipeline.workers.PRELOAD`):
loads the compiled kernel families the cache holds (:func:`.kernel_cache.load_cached`; all of
them, compiled here, where the cache folder cannot be written), so that every worker forked
from the server starts with them instead of loading them itself. A run fills the cache with its
recipe's families before it starts the server (:func:`.kernel_cache.ensure_compiled`)."""

from __future__ import annotations

from .kernel_cache import load_cached

load_cached()
