"""Loading the compiled (numba) kernels: jit options, one lock, compilation on first use into
:func:`cache_dir` (never the installation's folders). Kernels use numpy's error model and
per-function ``fastmath`` fixed at compile time, so results do not depend on the call."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, Generic, TypeVar

T = TypeVar("T")

#: fused multiply-adds allowed (reads, sums of products).
CONTRACT = frozenset({"contract"})
#: fused multiply-adds and reassociation (vectorised dot products).
REASSOC = frozenset({"reassoc", "contract"})

_LOCK = threading.RLock()

log = logging.getLogger(__name__)

#: environment variable naming the compiled kernels' cache folder (first in :func:`cache_dir`).
CACHE_ENV = "COLMAP_MIHO_CACHE_DIR"
#: numba's own cache folder setting (second in :func:`cache_dir`).
NUMBA_CACHE_ENV = "NUMBA_CACHE_DIR"

_CACHING = [True]  # whether the kernels being built use the on-disk cache (set by _kernel_cache)
_WARNED: set[str] = set()  # the unwritable folders warned about


def user_cache_root() -> Path:
    """The platform's user cache folder (``%LOCALAPPDATA%``, ``~/Library/Caches``,
    ``$XDG_CACHE_HOME`` or ``~/.cache``)."""
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"])
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    return Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"


def cache_dir() -> Path:
    """``$COLMAP_MIHO_CACHE_DIR``, else ``$NUMBA_CACHE_DIR``, else ``colmap-miho/numba`` under
    :func:`user_cache_root` (read at each call; empty counts as unset)."""
    for name in (CACHE_ENV, NUMBA_CACHE_ENV):
        if os.environ.get(name):
            return Path(os.environ[name]).expanduser().absolute()
    return (user_cache_root() / "colmap-miho" / "numba").absolute()


def writable(folder: Path) -> bool:
    """Whether ``folder`` exists or can be made, and a file can be written in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


@contextlib.contextmanager
def _kernel_cache() -> Iterator[None]:
    """numba's cache folder set to :func:`cache_dir` while kernels are built; no cache if unwritable."""
    from numba.core import config as numba_config

    config: Any = numba_config  # its settings are set from the environment at import
    folder = cache_dir()
    ok = writable(folder)
    if not ok and str(folder) not in _WARNED:
        _WARNED.add(str(folder))
        log.warning("cannot write the compiled kernels' cache in %s: the kernels compile again in every process "
                    "(set %s to a writable folder)", folder, CACHE_ENV)
    saved = config.CACHE_DIR
    config.CACHE_DIR, _CACHING[0] = str(folder), ok
    try:
        yield
    finally:
        config.CACHE_DIR, _CACHING[0] = saved, True


def jit(fastmath: frozenset[str] | None = None) -> Callable[[Callable], Any]:
    """numba's ``njit`` with the kernels' options: disk cache, no GIL, numpy's error model, ``fastmath``."""
    import numba

    cache = _CACHING[0]
    if fastmath is None:
        return numba.njit(cache=cache, nogil=True, error_model="numpy")
    return numba.njit(cache=cache, nogil=True, error_model="numpy", fastmath=set(fastmath))


def jit_helpers(namespace: dict[str, Any], helpers: Iterable[Callable],
                fastmath: frozenset[str] | None = None) -> None:
    """Replace ``helpers`` in a kernel module's namespace by their jitted versions (numba resolves callees there)."""
    j = jit(fastmath)
    namespace.update({f.__name__: j(f) for f in helpers})


class Kernels(Generic[T]):
    """A kernel module's jitted kernels, built on first call (thread-safe, once per process)."""

    def __init__(self, build: Callable[[], T]) -> None:
        self._build = build
        self._value: T | None = None

    def __call__(self) -> T:
        if self._value is None:
            with _LOCK:
                if self._value is None:
                    with _kernel_cache():
                        self._value = self._build()
        return self._value

    @property
    def loaded(self) -> bool:
        """Whether the kernels are loaded in this process (compiled or read from the cache)."""
        return self._value is not None

    def warm(self, example: Callable[[], object]) -> bool:
        """Load the kernels now by running ``example``; whether they loaded. Never raises (a
        failure shows where they are used)."""
        try:
            example()
        except Exception:  # noqa: BLE001 - warming is optional; the real call reports the error
            return False
        return self.loaded
