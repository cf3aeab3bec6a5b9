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
