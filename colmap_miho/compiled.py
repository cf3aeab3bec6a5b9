"""Loading the compiled (numba) kernels: the jit options, one lock, compilation on first use.

The kernel modules (:mod:`.filtering.compiled`, :mod:`.refinement.ncc.kernel`,
:mod:`.refinement.lsm.kernel`, :mod:`.refinement.rectify.kernel`) hold plain Python functions;
each wraps its build function in :class:`Kernels`, the module's ``KERNELS`` handle, which
imports numba and jits them the first time a kernel is called (compiled then, or loaded from
numba's on-disk cache, ``cache=True``), once per process, under one lock; a ``warm()`` loads
them ahead through :meth:`Kernels.warm`. numba is a required dependency: the CPU paths always run
compiled; the torch paths they mirror are the CUDA paths and the tests' references.

Where the compiled kernels are kept (:func:`cache_dir`): the folder ``COLMAP_MIHO_CACHE_DIR``
names, else numba's own ``NUMBA_CACHE_DIR``, else ``colmap-miho/numba`` in the user's cache
folder (``$XDG_CACHE_HOME`` or ``~/.cache`` on Linux, ``~/Library/Caches`` on macOS,
``%LOCALAPPDATA%`` on Windows): never the installation's own folders, so that a read-only
installation compiles once per user, not in every process. The kernels are built with numba's
cache folder set to it (numba's ``config.CACHE_DIR``, only while they are built: other numba
code of the process keeps its own). Where that folder cannot be written, the kernels compile
without a cache, in every process, and a warning says so once.

Every kernel uses numpy's error model (a float division by zero gives inf / nan, as in numpy,
not an exception); ``fastmath`` is chosen per function (:data:`CONTRACT`, :data:`REASSOC`)
and fixed when it compiles, so a kernel's results do not depend on the call.
"""

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
    """The user's cache folder of the platform: ``%LOCALAPPDATA%`` (Windows),
    ``~/Library/Caches`` (macOS), else ``$XDG_CACHE_HOME`` when absolute, else ``~/.cache``."""
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"])
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    return Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache"


def cache_dir() -> Path:
    """The folder of the compiled kernels' cache: ``$COLMAP_MIHO_CACHE_DIR``, else
    ``$NUMBA_CACHE_DIR``, else ``colmap-miho/numba`` under :func:`user_cache_root` (read from
    the environment at each call; an empty variable counts as unset)."""
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
    """numba's cache folder set to :func:`cache_dir` while kernels are built (numba picks a
    function's cache folder when it is jitted); without a writable folder, no cache."""
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
    """numba's ``njit`` with the kernels' options: on-disk cache (in :func:`cache_dir`, when
    built through :class:`Kernels`), no GIL, numpy's error model, and the ``fastmath`` flags
    given (none by default)."""
    import numba

    cache = _CACHING[0]
    if fastmath is None:
        return numba.njit(cache=cache, nogil=True, error_model="numpy")
    return numba.njit(cache=cache, nogil=True, error_model="numpy", fastmath=set(fastmath))


def jit_helpers(namespace: dict[str, Any], helpers: Iterable[Callable],
                fastmath: frozenset[str] | None = None) -> None:
    """Replace each of ``helpers`` in ``namespace`` (a kernel module's ``globals()``) by its
    jitted version: numba resolves a kernel's callees in its module's namespace when it
    compiles it."""
    j = jit(fastmath)
    namespace.update({f.__name__: j(f) for f in helpers})


class Kernels(Generic[T]):
    """A kernel module's jitted kernels, built by ``build`` on the first call (thread-safe,
    once per process), cached in :func:`cache_dir`."""

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
        """Load the kernels now by running ``example`` (a small synthetic call that reaches
        every kernel, so that each is compiled or read from the cache); returns whether they
        are loaded. Never raises: a process that cannot load them loads them when it uses them
        (where the error shows). The worker processes' forkserver warms them, so that every
        worker forked from it starts with them loaded."""
        try:
            example()
        except Exception:  # noqa: BLE001 - warming is optional; the real call reports the error
            return False
        return self.loaded
