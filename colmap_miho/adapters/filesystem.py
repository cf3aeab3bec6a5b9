"""File-system primitives every writer shares: writing a file whole or not at all, flushing it
and its folder, the process's umask, and the registry of working files a forced exit removes.

Writing whole or not at all: the content fills a new, uniquely named hidden file beside the
target (:func:`temp_beside`), which is flushed to disk (:func:`fsync_file`), renamed onto the
target (:func:`os.replace`, atomic on one file system) and the folder flushed (:func:`fsync_dir`,
so that the rename itself survives a power cut): the target is the old file or the new one,
never a part. :func:`write_atomic` does all of it for the run store's files;
:func:`~colmap_miho.adapters.staged_write.staged_write` adds what a user-visible output needs
(a full disk told apart, symlinks and devices, the user's permissions), and
:class:`~colmap_miho.adapters.working_copy.WorkingCopy` what the database needs.
"""

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
    """Delete the file ``path`` that this process made (a working or staged file), unless a
    symbolic link stands there now: that is not ours, and is left as it is (with a warning).
    A missing file is fine."""
    p = Path(path)
    if p.is_symlink():
        log.warning("%s is a symbolic link that colmap-miho did not make: left as it is", p)
        return
    with contextlib.suppress(FileNotFoundError):
        p.unlink()


def current_umask() -> int:
    """The process's umask (read without changing it): a new file's permissions are
    ``0o666 & ~current_umask()``."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temp_beside(target: Path) -> Path:
    """A new, empty, uniquely named hidden file ``.<name>.<random>.tmp`` beside ``target``
    (private: 0600), closed: never a fixed name, so two runs, or a user's own file, are never
    touched.

    Raises:
        OSError: the folder is missing or not writable, or the disk is full.
    """
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    return Path(name)


def fsync_file(path: str | os.PathLike) -> int:
    """Flush the closed file ``path`` to disk; returns its size in bytes."""
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())
        return os.fstat(fh.fileno()).st_size


def fsync_dir(folder: str | os.PathLike) -> None:
    """Flush ``folder``'s entries (a rename into it) to disk; a file system that cannot is
    ignored."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def replace_durably(tmp: Path, target: Path) -> None:
    """Rename the finished, flushed file ``tmp`` onto ``target`` (same folder: atomic) and
    flush the folder."""
    os.replace(tmp, target)
    fsync_dir(target.parent)


def write_atomic(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` whole or not at all: ``write(file)`` fills a new hidden file beside it
    (binary, private), which is flushed to disk and renamed onto ``path``; it is removed on any
    failure (``path`` then stays as it was).

    Raises:
        OSError: the folder cannot be written, or the disk is full (as the OS says it).
    """
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
