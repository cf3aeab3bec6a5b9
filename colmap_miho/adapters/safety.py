"""Safe handling of the user's database file: checks, working copies, atomic replace, backups.

The input database is never opened for writing (and never by pycolmap, which migrates the
schema on open). All work happens on a temporary copy beside the output; on success the copy
replaces the output with :func:`os.replace` (atomic on one file system). A crash, SIGKILL or
Ctrl-C at any point leaves the input byte-identical.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import stat
import struct
import tempfile
import time
from pathlib import Path

from ..errors import DatabaseError, UserError

log = logging.getLogger(__name__)

SQLITE_HEADER = b"SQLite format 3\x00"
SIDE_SUFFIXES = ("-wal", "-shm", "-journal")
# SQLite's lock bytes live at 1 GiB (PENDING_BYTE) + 2 + 510 shared bytes.
_LOCK_START = 0x40000000
_LOCK_LEN = 512


def check_database_path(path: str | os.PathLike) -> Path:
    """Check that ``path`` is an existing, readable SQLite file and return it as a Path.

    Nothing is created or opened for writing: a typo must not produce an empty database.

    Raises:
        DatabaseError: missing path, a folder, an unreadable file or not an SQLite file.
    """
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


def _locked_by_other_process(path: Path) -> bool:
    """True if another process holds an SQLite lock on ``path`` (POSIX F_GETLK probe).

    The probe opens the file read-only and only asks the kernel; it takes no lock.
    """
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
    """Refuse a database that another program holds open or that was not closed cleanly.

    COLMAP uses WAL journal mode: while it has the database open there are ``-wal`` and
    ``-shm`` side files, and a ``-wal`` left by a crash may hold data not yet in the main
    file, so copying the main file alone would lose it.

    Raises:
        DatabaseError: side files exist or another process holds an SQLite lock.
    """
    found = side_files(path)
    if found:
        names = ", ".join(f.name for f in found)
        raise DatabaseError(
            f"database {path} is in use by another program or was not closed cleanly "
            f"(found {names}); close COLMAP and retry"
        )
    if _locked_by_other_process(path):
        raise DatabaseError(f"database {path} is locked by another process; close it and retry")


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` (bytes only) and flush it to disk.

    Raises:
        DatabaseError: the source changed while it was copied.
    """
    before = src.stat()
    shutil.copyfile(src, dst)
    after = src.stat()
    if (before.st_size, before.st_mtime_ns) != (after.st_size, after.st_mtime_ns):
        raise DatabaseError(f"database {src} changed while it was copied; is another program writing it?")
    with open(dst, "rb+") as fh:
        os.fsync(fh.fileno())


def default_output_path(database: Path) -> Path:
    """``<dir>/<stem>.miho.db`` beside the input."""
    return database.with_name(f"{database.stem}.miho{database.suffix or '.db'}")


def backup_path(database: Path, now: float | None = None) -> Path:
    """A timestamped backup name beside ``database`` that does not exist yet."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    candidate = database.with_name(f"{database.name}.{stamp}.bak")
    k = 1
    while candidate.exists():
        candidate = database.with_name(f"{database.name}.{stamp}-{k}.bak")
        k += 1
    return candidate


def remove_with_side_files(path: Path) -> None:
    """Delete ``path`` and its SQLite side files, ignoring ones that do not exist."""
    for p in [path, *(Path(str(path) + s) for s in SIDE_SUFFIXES)]:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_replace(tmp: Path, dst: Path) -> None:
    """Move the finished working copy ``tmp`` onto ``dst`` atomically (same folder).

    The working copy must be closed (no side files); they are removed first.
    """
    for s in SIDE_SUFFIXES:
        side = Path(str(tmp) + s)
        if side.exists():
            raise DatabaseError(f"working copy {tmp} is still open ({side.name} exists)")
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, dst)
    _fsync_dir(dst.parent)


class WorkingCopy:
    """Plan and carry out the safe write of a processed database.

    Use as a context manager: ``path`` is a temporary copy of the input beside the output.
    Call :meth:`commit` after all writes (and after every database handle on ``path`` is
    closed) to move it onto the output. Leaving the block without commit, or with an
    exception, deletes the temporary copy; the input is never written.

    Args:
        database: the input database (checked, not opened).
        output: the output path, or None for ``<stem>.miho.db`` beside the input.
        in_place: replace the input itself, after copying it to a timestamped backup.
        overwrite: allow replacing an existing ``output``.
    """

    def __init__(self, database: Path, output: Path | None = None, *, in_place: bool = False,
                 overwrite: bool = False) -> None:
        self.database = Path(database)
        if in_place and output is not None and Path(output).resolve() != self.database.resolve():
            raise UserError("use either --output or --in-place, not both")
        self.in_place = in_place
        self.output = self.database if in_place else Path(output) if output else default_output_path(self.database)
        if not in_place:
            if self.output.resolve() == self.database.resolve():
                raise UserError(f"output {self.output} is the input database; use --in-place to replace it")
            if self.output.is_dir():
                raise UserError(f"output {self.output} is a folder; give a database file name")
            if self.output.exists() and not overwrite:
                raise UserError(f"output {self.output} exists; pass --overwrite to replace it")
            if not self.output.parent.is_dir():
                raise UserError(f"output folder does not exist: {self.output.parent}")
            if self.output.exists():
                check_not_in_use(self.output)
        self.backup: Path | None = None
        self.path: Path | None = None
        self.committed = False

    def __enter__(self) -> WorkingCopy:
        check_not_in_use(self.database)
        _warn_leftover_copies(self.output)
        if self.in_place:
            self.backup = backup_path(self.database)
            copy_file(self.database, self.backup)
            log.info("backup of the input written to %s", self.backup)
        fd, name = tempfile.mkstemp(prefix=f".{self.output.name}.", suffix=".tmp", dir=self.output.parent)
        os.close(fd)
        self.path = Path(name)
        try:
            copy_file(self.database, self.path)
            # mkstemp makes the file private (0600): give the result the input's permissions
            os.chmod(self.path, stat.S_IMODE(self.database.stat().st_mode))
        except BaseException:
            remove_with_side_files(self.path)
            raise
        return self

    def commit(self) -> Path:
        """Atomically move the working copy onto the output; returns the output path."""
        if self.path is None:
            raise RuntimeError("commit() outside the with block")
        if self.in_place:
            # The input must not have changed since it was backed up.
            check_not_in_use(self.database)
        atomic_replace(self.path, self.output)
        self.committed = True
        return self.output

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.path is not None and not self.committed:
            remove_with_side_files(self.path)


def leftover_copies(output: Path) -> list[Path]:
    """Hidden working copies of ``output`` that an earlier run left behind (a run killed with
    SIGKILL or a power cut cannot delete its own), oldest first. Copies that another process
    holds open (a run still going) are not listed."""
    found = [f for f in Path(output).parent.glob(f".{Path(output).name}.*.tmp")
             if f.is_file() and not _locked_by_other_process(f)]
    return sorted(found, key=lambda f: f.stat().st_mtime)


def _warn_leftover_copies(output: Path) -> None:
    found = leftover_copies(output)
    if found:
        mb = sum(g.stat().st_size for f in found for g in [f, *side_files(f)]) / 1e6
        log.warning(
            "%d working cop%s of %s left by an interrupted earlier run (%.0f MB with their "
            "-wal/-shm files; never the input or a result, safe to delete once no other "
            "colmap-miho run writes %s): %s",
            len(found), "y" if len(found) == 1 else "ies", output.name, mb, output.name,
            ", ".join(f.name for f in found),
        )

