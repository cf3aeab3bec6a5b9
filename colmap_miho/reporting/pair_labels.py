"""The one text key of an image pair in the comparison's tables and JSON: both names sorted, joined
by ``|``, with ``\\`` and ``|`` escaped so no two pairs share a key."""

from __future__ import annotations


def pair_label(name1: str, name2: str) -> str:
    """The key of the pair of images ``name1`` and ``name2`` (in either order)."""
    return "|".join(_escape(n) for n in sorted((str(name1), str(name2))))


def pair_names(label: str) -> tuple[str, ...]:
    """The names of a :func:`pair_label` key (older unescaped keys read the same unless a name held ``\\``)."""
    names, current, escaped = [], [], False
    for ch in label:
        if escaped:
            current.append(ch)
            escaped = False
        elif ch == "\\":
            escaped = True
        elif ch == "|":
            names.append("".join(current))
            current = []
        else:
            current.append(ch)
    names.append("".join(current))
    return tuple(names)


def _escape(name: str) -> str:
    return name.replace("\\", "\\\\").replace("|", "\\|")
