"""Imported by the workers' forkserver (:data:`colmap_miho.pipeline.workers.PRELOAD`) to load the
cached kernel families once, so every forked worker starts with them."""

from __future__ import annotations

from .kernel_cache import load_cached

load_cached()
