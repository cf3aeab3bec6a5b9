"""Checks shared by the frozen config dataclasses' ``__post_init__`` (pure: no I/O)."""

from __future__ import annotations

import dataclasses
import math

from .errors import InvalidInput


def require_finite(cfg) -> None:
    """Refuse ``inf`` and ``nan`` in every float field of the dataclass instance ``cfg``
    (a ``nan`` threshold compares False with everything and silently disables a check).

    Raises:
        ValueError: names the field and the value.
    """
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise InvalidInput(f"{f.name} must be a finite number, got {value}")


def require_at_most(name: str, value, limit, why: str) -> None:
    """Refuse ``value > limit`` for a field whose size drives memory use.

    Raises:
        ValueError: names the field, the value, the limit and ``why``.
    """
    if value is not None and value > limit:
        raise InvalidInput(f"{name} must be <= {limit} ({why}), got {value}")
