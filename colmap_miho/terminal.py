"""Text for the terminal: names read from files are data, never terminal control (a name holding a
newline or ANSI escape could forge or recolour a line). Printable characters stay as they are."""

from __future__ import annotations

import copy
import dataclasses
import logging
import unicodedata
from pathlib import PurePath

_NAMED = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}
#: Unicode controls that move or reorder text without being "Cc": line / paragraph separators,
#: the bidirectional marks, overrides and isolates (they can make a name read backwards).
_MOVING = frozenset("\u2028\u2029\u200e\u200f\u061c\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def _escape(ch: str) -> str:
    if ch in _NAMED:
        return _NAMED[ch]
    code = ord(ch)
    return f"\\x{code:02x}" if code <= 0xFF else f"\\u{code:04x}"


def printable(text: object, keep_newlines: bool = False) -> str:
    """``str(text)`` with control characters (C0, DEL, C1, Unicode separators, bidi overrides)
    escaped; ``keep_newlines`` keeps ``\\n``."""
    s = str(text)
    if s.isprintable() and not _MOVING.intersection(s):
        return s  # the usual case, fast
    return "".join(ch if (keep_newlines and ch == "\n")
                   or not (unicodedata.category(ch) == "Cc" or ch in _MOVING) else _escape(ch)
                   for ch in s)


def printable_fields(obj):
    """A copy of ``obj`` (nested dataclasses, dicts, lists, strings, paths) with strings made printable."""
    if isinstance(obj, (str, PurePath)):
        return printable(obj)
    if isinstance(obj, dict):
        return {k: printable_fields(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(printable_fields(v) for v in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = copy.copy(obj)  # a shallow copy (no __init__ checks), then its fields set in place
        for f in dataclasses.fields(obj):
            object.__setattr__(out, f.name, printable_fields(getattr(obj, f.name)))
        return out
    return obj


class PrintableFormatter(logging.Formatter):
    """A :class:`logging.Formatter` escaping control characters in messages and tracebacks."""

    def formatMessage(self, record: logging.LogRecord) -> str:  # noqa: N802 - logging's name
        record.message = printable(record.message)
        return super().formatMessage(record)

    def formatException(self, ei) -> str:  # noqa: N802 - logging's name
        return printable(super().formatException(ei), keep_newlines=True)
