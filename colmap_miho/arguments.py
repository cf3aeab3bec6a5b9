"""The public Python API's arguments checked with the command line's rules (pure): every public
entry point checks ``workers``, ``seed`` and paths here, so ``workers=10**6`` or a ``None`` path is
refused with a message instead of failing deep inside."""

from __future__ import annotations

import numbers
import os

from .errors import InvalidInput
from .validation import OPTION_BOUNDS, Bound, check_value

#: ``filter_matches``' seed only seeds numpy (the pipeline passes each pair a 32-bit
#: ``SeedSequence`` state); the CLI's ``--seed`` is 31 bits because COLMAP's is a C ``int``.
FILTER_SEED_BOUND = Bound(0, 2**32 - 1, "a 32-bit seed")


def check_integer(name: str, value, bound: Bound | None = None, *, optional: bool = False) -> int | None:
    """``value`` as an ``int`` within ``bound``; a bool, float, string or None (unless ``optional``)
    is refused, as by the CLI's ``type=int`` (InvalidInput)."""
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InvalidInput(f"{name} must be an integer, got {value!r}")
    value = int(value)
    if bound is not None:
        check_value(name, value, bound)
    return value


def check_workers(workers, name: str = "workers") -> int | None:
    """``workers``: None (all cores) or an integer in ``OPTION_BOUNDS["workers"]`` (as ``--workers``)."""
    return check_integer(name, workers, OPTION_BOUNDS["workers"], optional=True)


def check_seed(seed, name: str = "seed", *, optional: bool = False) -> int | None:
    """``seed``: an integer in ``OPTION_BOUNDS["seed"]`` (32 bits, as ``--seed``)."""
    return check_integer(name, seed, OPTION_BOUNDS["seed"], optional=optional)


def check_path(name: str, value, *, optional: bool = False) -> None:
    """Refuse a ``value`` that is not a non-empty ``str`` or ``os.PathLike`` (None only if ``optional``)."""
    if value is None and optional:
        return
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if not isinstance(value, str) or not value:
        raise InvalidInput(f"{name} must be a path (str or os.PathLike), got {value!r}")
    if "\x00" in value:
        raise InvalidInput(f"{name} must not hold a NUL character, got {value!r}")


def check_paths(*, optional: tuple[str, ...] = (), **paths) -> None:
    """:func:`check_path` of each keyword (``name=value``); those named in ``optional`` may be None."""
    for name, value in paths.items():
        check_path(name, value, optional=name in optional)
