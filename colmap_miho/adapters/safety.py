"""Safe handling of the user's database file: checks, read copies, backups. The input is never
opened for writing, nor by pycolmap (which migrates the schema on open)."""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import sqlite3
import struct
import time
from collections.abc import Callable
from pathlib import Path

from ..errors import DatabaseError, UserError
from .filesystem import WORKING_FILES, fsync_file, remove_own_file
from .staged_write import disk_full_error, is_disk_full

log = logging.getLogger(__name__)

SQLITE_HEADER = b"SQLite format 3\x00"
SIDE_SUFFIXES = ("-wal", "-shm", "-journal")
# SQLite's lock bytes live at 1 GiB (PENDING_BYTE) + 2 + 510 shared bytes.
_LOCK_START = 0x40000000
_LOCK_LEN = 512

#: In-place backups not yet needed: backup -> (the input, its identity when backed up); a forced
#: exit removes those whose input was not replaced (see :func:`remove_working_files`).
PENDING_BACKUPS: dict[Path, tuple[Path, tuple]] = {}


#: What a forced exit must tell besides "working files removed" (e.g. where a refine run's
#: finished work is kept and that ``--resume`` continues it): callables returning one note
#: each ("" for none), registered for the time they apply (see :func:`exit_note`).
EXIT_NOTES: list[Callable[[], str]] = []


@contextlib.contextmanager
def exit_note(note: Callable[[], str]):
    """Register ``note`` in :data:`EXIT_NOTES` for the block."""
    EXIT_NOTES.append(note)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            EXIT_NOTES.remove(note)


def exit_notes() -> list[str]:
    """The non-empty notes of :data:`EXIT_NOTES` (a note that fails is left out: the exit goes on)."""
    out = []
    for note in list(EXIT_NOTES):
        with contextlib.suppress(Exception):
            text = note()
            if text:
                out.append(text)
    return out


def remove_working_files() -> list[Path]:
    """Delete this process's registered working files and their SQLite side files (a forced exit
    runs no ``finally``); returns those that existed."""
    removed = []
    for path in list(WORKING_FILES):
        if path.exists():
            removed.append(path)
        with contextlib.suppress(OSError):
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                remove_with_side_files(path)
        WORKING_FILES.discard(path)
    for backup, (target, identity) in list(PENDING_BACKUPS.items()):
        with contextlib.suppress(OSError):
            if file_identity(target) == identity:  # the input was not replaced: no need for it
                backup.unlink()
                removed.append(backup)
        PENDING_BACKUPS.pop(backup, None)
    return removed


def check_database_path(path: str | os.PathLike) -> Path:
    """``path`` as a Path after checking it is an existing, readable SQLite file, without creating
    or writing anything (a typo must not make an empty database). DatabaseError otherwise."""
    p = Path(path)
    if not p.exists():
        raise DatabaseError(f"database not found: {p}")
    if not p.is_file():
        raise DatabaseError(f"database path is not a file: {p}")
    try:
        with open(p, "rb") as fh:
            header = fh.read(len(SQLITE_HEADER))
    except OSError as exc:
        raise DatabaseError(f"cannot read database {p}: {exc.strerror}") from None
    if header != SQLITE_HEADER:
        raise DatabaseError(f"not a COLMAP database (not an SQLite file): {p}")
    return p


def side_files(path: Path) -> list[Path]:
    """SQLite side files (-wal, -shm, -journal) that exist beside ``path``."""
    return [Path(str(path) + s) for s in SIDE_SUFFIXES if Path(str(path) + s).exists()]


def locked_by_other_process(path: Path) -> bool:
    """Whether another process holds an SQLite lock on ``path`` (an F_GETLK probe; takes no lock)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        # struct flock {short l_type; short l_whence; off_t l_start; off_t l_len; pid_t l_pid;}
        req = struct.pack("hhqqi", fcntl.F_WRLCK, os.SEEK_SET, _LOCK_START, _LOCK_LEN, 0)
        try:
            res = fcntl.fcntl(fd, fcntl.F_GETLK, req + b"\0" * 4)
        except OSError:  # pragma: no cover - file systems without POSIX locks
            return False
        l_type = struct.unpack("hhqqi", res[: struct.calcsize("hhqqi")])[0]
        return l_type != fcntl.F_UNLCK
    finally:
        os.close(fd)


def check_not_in_use(path: Path) -> None:
    """Refuse a database another program holds open, or with a hot journal left by a crash (a
    non-empty ``-wal`` or ``-journal`` nobody holds: copying the main file alone would lose data).
    DatabaseError."""
    found = side_files(path)
    if locked_by_other_process(path):
        names = "".join(f", {f.name} exists" for f in found)
        raise DatabaseError(f"database {path} is in use by another program (locked by another process{names}); "
                            "close it (COLMAP, a viewer) and retry")
    hot = [f for f in found if not f.name.endswith("-shm") and _size(f) > 0]
    if hot:
        raise DatabaseError(
            f"database {path} was not closed cleanly: {hot[0].name} holds {_size(hot[0])} bytes of "
            f"changes not yet in the main file; open it once with COLMAP or `sqlite3 {path} "
            f"'PRAGMA wal_checkpoint;'` to apply them, then retry")


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def check_free_space(folder: Path, needed: int, what: str) -> None:
    """Refuse to start with less than ``needed`` bytes free in ``folder`` (UserError naming the sizes)."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:  # pragma: no cover - unknown: let the copy itself fail cleanly
        return
    if free < needed:
        raise UserError(f"not enough free space in {folder}: {what} needs about {needed / 1e6:.0f} MB, "
                        f"{free / 1e6:.0f} MB free; free some space or write elsewhere")


def read_copy(database: str | os.PathLike, dst: Path) -> Path:
    """Check a database (exists, SQLite, not in use), check free space and copy it to ``dst``;
    returns the checked input path. Only the copy may then be opened."""
    src = check_database_path(database)
    check_not_in_use(src)
    check_free_space(Path(dst).parent, 2 * _size(src), f"a working copy of {src}")
    WORKING_FILES.add(Path(dst))
    copy_file(src, Path(dst))
    check_integrity(Path(dst), src)
    return src


def check_integrity(copy: Path, name: Path) -> None:
    """``PRAGMA quick_check`` on ``copy`` (never the user's file) before pycolmap, which aborts on
    some damaged files, opens it; DatabaseError naming ``name``."""
    try:
        con = sqlite3.connect(f"file:{Path(copy).resolve()}?mode=rw", uri=True)
        try:
            rows = con.execute("PRAGMA quick_check").fetchall()
        finally:
            con.close()
    except sqlite3.Error as exc:
        raise DatabaseError(f"database {name} is damaged or truncated (SQLite: {exc}); restore it "
                            "from a backup or rebuild it") from None
    if rows != [("ok",)]:
        raise DatabaseError(f"database {name} is damaged (SQLite quick_check: {rows[0][0]}); restore "
                            "it from a backup or rebuild it")


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` (never through a link there) and flush. DatabaseError if the source
    changed meanwhile; RunFailed for a full disk; UserError otherwise."""
    before = src.stat()
    if os.path.islink(dst):
        raise UserError(f"{dst} is a symbolic link (to {os.readlink(dst)}), where colmap-miho writes a file of "
                        "its own; nothing was written through it: remove it and run again")
    try:
        # O_NOFOLLOW: a link put there after the look is not followed either
        fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o666)
        with open(src, "rb") as fsrc, open(fd, "wb") as fdst:
            shutil.copyfileobj(fsrc, fdst, COPY_BUFFER_BYTES)
        fsync_file(dst)
    except OSError as exc:
        with contextlib.suppress(OSError):
            Path(dst).unlink()
        if is_disk_full(exc):  # the message a full disk (or a file-size limit) has everywhere
            raise disk_full_error(Path(dst).parent, f"copying {src}", exc) from None
        raise UserError(f"cannot copy database {src} to {Path(dst).parent}: "
                        f"{exc.strerror or exc}; free some space or choose a writable folder") from None
    after = src.stat()
    if (before.st_size, before.st_mtime_ns) != (after.st_size, after.st_mtime_ns):
        with contextlib.suppress(OSError):
            Path(dst).unlink()
        raise DatabaseError(f"database {src} changed while it was copied; is another program writing it?")


#: Bytes per read and write of :func:`copy_file`.
COPY_BUFFER_BYTES = 1 << 22


def file_identity(path: Path) -> tuple:
    """What must not change under an in-place run: device, inode, size, mtime and SQLite's header."""
    st = os.stat(path)
    with open(path, "rb") as fh:
        header = fh.read(100)
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, header


def default_output_path(database: Path) -> Path:
    """``<dir>/<stem>.miho.db`` beside the input."""
    return database.with_name(f"{database.stem}.miho{database.suffix or '.db'}")


def backup_path(database: Path, now: float | None = None) -> Path:
    """A timestamped backup name beside ``database`` that does not exist yet."""
    return unused_stamped_name(database, lambda stamp: f"{database.name}.{stamp}.bak", now)


def unused_stamped_name(database: Path, name_for, now: float | None = None) -> Path:
    """``database.with_name(name_for(stamp))`` with the local time as stamp, suffixed until unused."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    candidate = database.with_name(name_for(stamp))
    k = 1
    while os.path.lexists(candidate):
        candidate = database.with_name(name_for(f"{stamp}-{k}"))
        k += 1
    return candidate


def remove_with_side_files(path: Path) -> None:
    """Delete ``path`` and its SQLite side files, skipping missing ones and links."""
    for p in [path, *(Path(str(path) + s) for s in SIDE_SUFFIXES)]:
        remove_own_file(p)
