"""Research variants of a stage config: a copy with some of its class constants changed (the
constants are not recipe keys; tests and benchmarks measure the rules they switch)."""

from __future__ import annotations

import copy
import dataclasses
from enum import Enum


def variant(cfg, **constants):
    """A copy of the frozen config ``cfg`` whose class constants ``constants`` take the given
    values (a string is parsed for an enum constant)."""
    out = copy.copy(cfg)
    fields = {f.name for f in dataclasses.fields(cfg)}
    for name, value in constants.items():
        if name in fields or not hasattr(type(cfg), name):
            raise AttributeError(f"{type(cfg).__name__}.{name} is not a class constant")
        const = getattr(type(cfg), name)
        if isinstance(const, Enum):
            value = type(const).parse(value, name)  # type: ignore[attr-defined]
        object.__setattr__(out, name, value)
    return out


def configured(cls, base=None, **values):
    """``cls(**fields)`` (or ``base`` with them replaced) with the class constants among
    ``values`` changed by :func:`variant`: one call for a benchmark's ``--variant`` strings."""
    names = {f.name for f in dataclasses.fields(cls)}
    fields = {k: v for k, v in values.items() if k in names}
    if base is None:
        return variant(cls(**fields), **{k: v for k, v in values.items() if k not in names})
    kept = {k: v for k, v in vars(base).items() if k not in names}  # base's own variant constants
    kept.update((k, v) for k, v in values.items() if k not in names)
    return variant(dataclasses.replace(base, **fields), **kept)
