"""One place that resolves the paths a command reads and writes and refuses any overlap.

A command that writes a file where it reads one destroys the user's data (``refine --json
x.db --database x.db`` used to replace the database with the JSON summary). Every command
therefore lists its inputs and outputs (``paths(args)`` in its module, see
:mod:`colmap_miho.cli`) and :func:`check_distinct` compares them before any work starts:
paths are resolved (symbolic links followed, ``..`` removed) and existing files are compared
by device and inode, so a symlink or a hard link to the database counts as the database.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from ..errors import UserError

#: SQLite's side files of a database: writing one of these corrupts the database.
SQLITE_SIDE_SUFFIXES = ("-wal", "-shm", "-journal")

PathArg = str | os.PathLike | None


def resolve(path: str | os.PathLike) -> Path:
    """The absolute, symlink-free path that writing ``path`` would reach.

    Existing paths are resolved completely; for a missing one its folder is resolved and the
    name appended (a dangling symlink resolves to its target)."""
    p = Path(path).expanduser()
    try:
        return p.resolve(strict=False)
    except (OSError, RuntimeError):  # symlink loop
        return Path(os.path.abspath(p))


def identity(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of the file ``path`` reaches (symlinks followed), or None if it
    does not exist."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True if ``a`` and ``b`` reach the same file: equal device and inode when both exist,
    else equal resolved paths."""
    ia, ib = identity(a), identity(b)
    if ia is not None and ib is not None:
        return ia == ib
    return resolve(a) == resolve(b)


def model_files(folder: PathArg, label: str) -> dict[str, Path]:
    """The COLMAP model files a command writes into ``folder`` (``cameras``, ``images``,
    ``points3D``, ``rigs``, ``frames``; .bin and .txt), labelled ``"<label> (<name>)"`` for
    :func:`check_distinct`; empty when ``folder`` is None."""
    if folder is None:
        return {}
    names = [f"{stem}{ext}" for stem in ("cameras", "images", "points3D", "rigs", "frames")
             for ext in (".bin", ".txt")]
    return {f"{label} ({name})": Path(folder) / name for name in names}


def _clean(paths: Mapping[str, PathArg]) -> dict[str, Path]:
    return {label: Path(p) for label, p in paths.items() if p is not None and str(p) != ""}


def check_distinct(inputs: Mapping[str, PathArg], outputs: Mapping[str, PathArg]) -> None:
    """Refuse a command whose outputs overlap its inputs or each other.

    Args:
        inputs: label (the option, e.g. ``"--database"``) -> a file or folder the command
            reads; None entries are skipped. An input database also protects its SQLite side
            files (``-wal``, ``-shm``, ``-journal``).
        outputs: label -> a file the command writes (replaced if it exists); None skipped.

    Raises:
        UserError: (exit 2) an output is the same file as an input, one of its SQLite side
            files, or another output; an output is an existing folder. The message names
            both options and paths and says to choose another path.
    """
    ins, outs = _clean(inputs), _clean(outputs)
    for out_label, out in outs.items():
        if out.is_dir():
            raise UserError(f"{out_label} {out} is a folder; give a file name")
        for in_label, inp in ins.items():
            if same_file(out, inp):
                raise UserError(f"{out_label} {out} is the same file as {in_label} {inp}; it would "
                                f"be overwritten: choose another {out_label} path")
            for suffix in SQLITE_SIDE_SUFFIXES:
                if resolve(out) == Path(str(resolve(inp)) + suffix):
                    raise UserError(f"{out_label} {out} is SQLite's {suffix} file of {in_label} "
                                    f"{inp}: choose another {out_label} path")
    labels = list(outs)
    for k, a in enumerate(labels):
        for b in labels[k + 1:]:
            if same_file(outs[a], outs[b]):
                raise UserError(f"{a} and {b} are the same file ({outs[a]}): choose another {b} path")
