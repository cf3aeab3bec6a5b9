"""The arguments of the public Python API, checked with the command line's rules.

The CLI bounds its numeric options (:data:`~colmap_miho.validation.OPTION_BOUNDS`) and argparse
refuses a value of the wrong type; a Python caller passes values straight in. Every public
entry point (``refine_database``, ``run_mapping``, ``compare_databases``, ``run_from_images``,
``extract_and_match``, ``build_report``, ``filter_matches``) checks its ``workers``, ``seed``
and paths here first, so that ``workers=10**6`` is refused instead of becoming a million
threads, and ``None`` where a path belongs is named instead of failing deep inside.
Pure: no I/O.
"""

from __future__ import annotations

import numbers
import os

from .errors import InvalidInput
from .validation import OPTION_BOUNDS, Bound, check_value

#: ``filter_matches``' seed only seeds numpy (the pipeline passes each pair a 32-bit
#: ``SeedSequence`` state); the CLI's ``--seed`` is 31 bits because COLMAP's is a C ``int``.
FILTER_SEED_BOUND = Bound(0, 2**32 - 1, "a 32-bit seed")


def check_integer(name: str, value, bound: Bound | None = None, *, optional: bool = False) -> int | None:
    """``value`` as an ``int`` (numpy integers too), within ``bound`` when given.

    A bool, a float (even ``2.0``), a string or ``None`` (unless ``optional``) is refused: the
    CLI's ``type=int`` refuses them too.

    Raises:
        InvalidInput: ``"<name> must be an integer, got '2'"`` or
            ``"<name> must be in [lo, hi] (why), got value"``.
    """
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
    """``value`` is a path: a non-empty ``str`` or an ``os.PathLike`` (``None`` only when
    ``optional``). Whether the file exists is the caller's to say, with its own message.

    Raises:
        InvalidInput: ``"<name> must be a path (str or os.PathLike), got None"``.
    """
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
