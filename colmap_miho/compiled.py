"""Loading the compiled (numba) kernels: the jit options, one lock, compilation on first use.

The kernel modules (:mod:`.filtering.compiled`, :mod:`.refinement.ncc.kernel`,
:mod:`.refinement.lsm.kernel`, :mod:`.refinement.rectify.kernel`) hold plain Python functions;
each wraps its build function in :class:`Kernels`, the module's ``KERNELS`` handle, which
imports numba and jits them the first time a kernel is called (compiled then, or loaded from
numba's on-disk cache, ``cache=True``), once per process, under one lock; a ``warm()`` loads
them ahead through :meth:`Kernels.warm`. numba is a required dependency: the CPU paths always run
compiled; the torch paths they mirror are the CUDA paths and the tests' references.

Every kernel uses numpy's error model (a float division by zero gives inf / nan, as in numpy,
not an exception); ``fastmath`` is chosen per function (:data:`CONTRACT`, :data:`REASSOC`)
and fixed when it compiles, so a kernel's results do not depend on the call.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any, Generic, TypeVar

T = TypeVar("T")

#: fused multiply-adds allowed (reads, sums of products).
CONTRACT = frozenset({"contract"})
#: fused multiply-adds and reassociation (vectorised dot products).
REASSOC = frozenset({"reassoc", "contract"})

_LOCK = threading.RLock()


def jit(fastmath: frozenset[str] | None = None) -> Callable[[Callable], Any]:
    """numba's ``njit`` with the kernels' options: on-disk cache, no GIL, numpy's error
    model, and the ``fastmath`` flags given (none by default)."""
    import numba

    if fastmath is None:
        return numba.njit(cache=True, nogil=True, error_model="numpy")
    return numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=set(fastmath))


def jit_helpers(namespace: dict[str, Any], helpers: Iterable[Callable],
                fastmath: frozenset[str] | None = None) -> None:
    """Replace each of ``helpers`` in ``namespace`` (a kernel module's ``globals()``) by its
    jitted version: numba resolves a kernel's callees in its module's namespace when it
    compiles it."""
    j = jit(fastmath)
    namespace.update({f.__name__: j(f) for f in helpers})


class Kernels(Generic[T]):
    """A kernel module's jitted kernels, built by ``build`` on the first call (thread-safe,
    once per process)."""

    def __init__(self, build: Callable[[], T]) -> None:
        self._build = build
        self._value: T | None = None

    def __call__(self) -> T:
        if self._value is None:
            with _LOCK:
                if self._value is None:
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
