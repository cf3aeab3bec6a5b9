"""File-system primitives every writer shares: writing whole or not at all (a hidden file beside the
target, flushed, renamed, folder flushed), the umask, and the working files a forced exit removes."""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

log = logging.getLogger(__name__)

#: Working files of this process (working copies, staged outputs, private folders) that a forced
#: exit must remove (see :func:`~colmap_miho.adapters.safety.remove_working_files`).
WORKING_FILES: set[Path] = set()


def remove_own_file(path: str | os.PathLike) -> None:
    """Delete ``path`` this process made, unless a symbolic link stands there now (not ours: warned)."""
    p = Path(path)
    if p.is_symlink():
        log.warning("%s is a symbolic link that colmap-miho did not make: left as it is", p)
        return
    with contextlib.suppress(FileNotFoundError):
        p.unlink()


def current_umask() -> int:
    """The process's umask, read without changing it."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temp_beside(target: Path) -> Path:
    """A new, empty, private hidden file ``.<name>.<random>.tmp`` beside ``target`` (never a fixed
    name); OSError for an unwritable folder or full disk."""
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    return Path(name)


def fsync_file(path: str | os.PathLike) -> int:
    """Flush the closed file ``path`` to disk; returns its size in bytes."""
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())
        return os.fstat(fh.fileno()).st_size


def fsync_dir(folder: str | os.PathLike) -> None:
    """Flush ``folder``'s entries to disk (ignored where unsupported)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def replace_durably(tmp: Path, target: Path) -> None:
    """Rename the flushed ``tmp`` onto ``target`` (same folder: atomic) and flush the folder."""
    os.replace(tmp, target)
    fsync_dir(target.parent)


def write_atomic(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` whole or not at all: ``write(file)`` fills a private hidden file, flushed and
    renamed onto ``path``, removed on failure."""
    tmp = temp_beside(path)
    try:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        replace_durably(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            remove_own_file(tmp)
        raise
