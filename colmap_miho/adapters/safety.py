"""Safe handling of the user's database file: checks, working copies, atomic replace, backups.

The input database is never opened for writing (and never by pycolmap, which migrates the
schema on open). All work happens on a temporary copy beside the output; on success the copy
replaces the output with :func:`os.replace` (atomic on one file system). A crash, SIGKILL or
Ctrl-C at any point leaves the input byte-identical.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import shutil
import sqlite3
import stat
import struct
import tempfile
import time
from pathlib import Path

from ..errors import DatabaseError, RunFailed, UserError

log = logging.getLogger(__name__)

SQLITE_HEADER = b"SQLite format 3\x00"
SIDE_SUFFIXES = ("-wal", "-shm", "-journal")
# SQLite's lock bytes live at 1 GiB (PENDING_BYTE) + 2 + 510 shared bytes.
_LOCK_START = 0x40000000
_LOCK_LEN = 512

#: Working files of this process that a forced exit must remove (see :func:`remove_working_files`).
_WORKING_FILES: set[Path] = set()
#: In-place backups not yet needed: backup -> (the input, its identity when backed up).
_PENDING_BACKUPS: dict[Path, tuple[Path, tuple]] = {}


def remove_working_files() -> list[Path]:
    """Delete this process's registered working files (working copies, read copies) and their
    SQLite side files; returns those that existed. For a forced exit (a SIGTERM that arrives
    while a long COLMAP call holds the interpreter), where no ``finally`` block runs."""
    removed = []
    for path in list(_WORKING_FILES):
        if path.exists():
            removed.append(path)
        with contextlib.suppress(OSError):
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                remove_with_side_files(path)
        _WORKING_FILES.discard(path)
    for backup, (target, identity) in list(_PENDING_BACKUPS.items()):
        with contextlib.suppress(OSError):
            if file_identity(target) == identity:  # the input was not replaced: no need for it
                backup.unlink()
                removed.append(backup)
        _PENDING_BACKUPS.pop(backup, None)
    return removed


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

    COLMAP uses WAL journal mode: while a program has the database open it holds an SQLite
    lock (probed without taking it) and there are ``-wal``/``-shm`` side files; a non-empty
    ``-wal`` (or rollback ``-journal``) that nobody holds open is a hot journal left by a crash:
    it holds data not yet in the main file, so copying the main file alone would use stale
    data. An empty ``-wal`` and a ``-shm`` without a lock (what a read-only viewer leaves)
    hold nothing and are safe.

    Raises:
        DatabaseError: another process holds a lock, or a hot journal exists; the message
            names the file and the way out.
    """
    found = side_files(path)
    if _locked_by_other_process(path):
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
    """Refuse to start when ``folder``'s file system has less than ``needed`` bytes free.

    Raises:
        UserError: not enough space; the message names the folder, both sizes and ``what``.
    """
    try:
        free = shutil.disk_usage(folder).free
    except OSError:  # pragma: no cover - unknown: let the copy itself fail cleanly
        return
    if free < needed:
        raise UserError(f"not enough free space in {folder}: {what} needs about {needed / 1e6:.0f} MB, "
                        f"{free / 1e6:.0f} MB free; free some space or write elsewhere")


def read_copy(database: str | os.PathLike, dst: Path) -> Path:
    """The safe way to read a database: check it (exists, SQLite, not in use, no hot journal),
    check the free space, and copy it to ``dst``; returns the checked input path. Only the
    copy may then be opened (pycolmap migrates the schema on open).

    Raises:
        DatabaseError / UserError: see :func:`check_database_path`, :func:`check_not_in_use`,
            :func:`check_free_space`, :func:`copy_file`.
    """
    src = check_database_path(database)
    check_not_in_use(src)
    check_free_space(Path(dst).parent, 2 * _size(src), f"a working copy of {src}")
    _WORKING_FILES.add(Path(dst))
    copy_file(src, Path(dst))
    check_integrity(Path(dst), src)
    return src


def check_integrity(copy: Path, name: Path) -> None:
    """SQLite's ``PRAGMA quick_check`` on the copy ``copy`` of the user's database ``name``
    (with Python's sqlite3, closed again: a WAL-mode copy is left without side files): a
    truncated or damaged file is an error before pycolmap, which aborts the process on some
    damaged files, ever opens it. Never call it on the user's file itself.

    Raises:
        DatabaseError: damaged or not a database; the message names ``name``.
    """
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
    """Copy ``src`` to ``dst`` (bytes only) and flush it to disk.

    Raises:
        DatabaseError: the source changed while it was copied.
        UserError: the copy failed (disk full, read-only folder); ``dst`` is removed and the
            message names the folder.
    """
    before = src.stat()
    try:
        shutil.copyfile(src, dst)
        with open(dst, "rb+") as fh:
            os.fsync(fh.fileno())
    except OSError as exc:
        with contextlib.suppress(OSError):
            Path(dst).unlink()
        raise UserError(f"cannot copy database {src} to {Path(dst).parent}: "
                        f"{exc.strerror or exc}; free some space or choose a writable folder") from None
    after = src.stat()
    if (before.st_size, before.st_mtime_ns) != (after.st_size, after.st_mtime_ns):
        with contextlib.suppress(OSError):
            Path(dst).unlink()
        raise DatabaseError(f"database {src} changed while it was copied; is another program writing it?")


DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
#: What SQLite (through pycolmap's RuntimeError) says when the disk is full.
SQLITE_FULL_TEXT = ("database or disk is full", "disk i/o error", "no space left on device")


def is_disk_full(exc: BaseException) -> bool:
    """True for a full disk: ENOSPC / EDQUOT / EFBIG, SQLite's ``SQLITE_FULL`` and pycolmap's
    ``RuntimeError: ... database or disk is full``."""
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
        return True
    if isinstance(exc, (OSError, RuntimeError, sqlite3.Error)):  # h5py's OSError carries no errno
        text = str(exc).lower()
        return any(t in text for t in SQLITE_FULL_TEXT)
    return False


def disk_full_error(folder: Path, what: str) -> RunFailed:
    """The one-line error of a full disk: it names the file system's folder and what was kept."""
    free = ""
    with contextlib.suppress(OSError):
        free = f" ({shutil.disk_usage(folder).free / 1e6:.1f} MB free)"
    return RunFailed(f"disk full in {folder}{free} while {what}; nothing was written under the output name "
                     "and the working files were removed: free some space and retry")


def write_target(path: str | os.PathLike) -> Path:
    """The file that writing ``path`` should replace: a symlink's target (the link is kept and
    shows the new content), else ``path`` itself."""
    p = Path(path)
    return p.resolve() if p.is_symlink() else p


def _new_staging_name(target: Path) -> Path:
    """A new, empty, uniquely named hidden file ``.<name>.<random>.tmp`` beside ``target``
    (never a fixed name: two runs, or a user's own file, are never touched)."""
    try:
        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except FileNotFoundError:
        raise UserError(f"cannot write {target}: its folder {target.parent} does not exist") from None
    except OSError as exc:
        if is_disk_full(exc):
            raise disk_full_error(target.parent, f"writing {target}") from None
        raise UserError(f"cannot write {target}: {exc.strerror or exc}") from None
    os.close(fd)
    return Path(name)


def _check_written(tmp: Path, target: Path, expected_size: int | None) -> None:
    """Flush ``tmp`` to disk and check its size (``expected_size``, else > 0): a native writer
    that hits a full disk often says nothing and leaves a short or empty file."""
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
        size = os.fstat(fh.fileno()).st_size
    if (size != expected_size) if expected_size is not None else size == 0:
        want = f"{expected_size} bytes expected" if expected_size is not None else "an empty file"
        raise disk_full_error(target.parent, f"writing {target} ({size} bytes written, {want})")


@contextlib.contextmanager
def staged_write(path: str | os.PathLike, *, expected_size=None):
    """Write one output file whole or not at all: the one rule of every file a command writes.

    Yields a new, uniquely named hidden file beside the target (see :func:`write_target`: a
    symlink's target is written and the link kept) for the caller (or a native writer) to
    fill. After the block it is flushed to disk, its size checked (``expected_size``: bytes,
    or a callable taking the written path, e.g. :func:`ply_size`; default: not empty), and
    renamed onto the target; on any failure it is removed and the target left as it was.

    Raises:
        RunFailed: disk full (one line naming the folder), or a short write.
        UserError: a missing or read-only folder.
    """
    target = write_target(path)
    tmp = _new_staging_name(target)
    _WORKING_FILES.add(tmp)
    try:
        try:
            yield tmp
            try:
                expected = expected_size(tmp) if callable(expected_size) else expected_size
            except ValueError as exc:  # no readable header: cut short
                raise disk_full_error(target.parent, f"writing {target} ({exc})") from None
            _check_written(tmp, target, expected)
            os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private
            os.replace(tmp, target)
        except OSError as exc:
            if is_disk_full(exc):
                raise disk_full_error(target.parent, f"writing {target}") from None
            raise
        except RuntimeError as exc:
            if is_disk_full(exc):
                raise disk_full_error(target.parent, f"writing {target}") from None
            raise
        _fsync_dir(target.parent)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
        _WORKING_FILES.discard(tmp)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """:func:`staged_write` of ``data``; returns the path written (a symlink's target)."""
    with staged_write(path, expected_size=len(data)) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return write_target(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """:func:`staged_write` of ``text`` (UTF-8); returns the path written."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def ply_size(path: Path) -> int:
    """The size a binary PLY file must have by its own header (vertex count times the bytes of
    its properties, plus the header): checks the output of a native PLY writer.

    Raises:
        ValueError: no readable header (a write cut short before it ended).
    """
    sizes = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
             "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        raise ValueError(f"{len(head)} bytes, no complete PLY header")
    total, count, row = end + len(b"end_header\n"), 0, 0
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if words[:1] == ["element"]:
            total += count * row
            count, row = int(words[2]), 0
        elif words[:1] == ["property"] and words[1] != "list":
            row += sizes.get(words[1], 0)
    return total + count * row


def write_model_atomic(reconstruction, folder: str | os.PathLike, *, text: bool = False) -> Path:
    """Write a ``pycolmap.Reconstruction`` into ``folder`` without trusting the native writer:
    it writes into a new hidden folder beside ``folder``, which is read back (the counts of
    cameras, images and points must match), then each file is renamed into ``folder`` and the
    model files of the other format (.bin / .txt) left there are removed.

    Raises:
        RunFailed: disk full (the read-back fails or differs); ``folder`` is left as it was.
    """
    import pycolmap

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        stage = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    except OSError as exc:
        if is_disk_full(exc):
            raise disk_full_error(folder.parent, f"writing the model {folder}") from None
        raise
    _WORKING_FILES.add(stage)
    try:
        try:
            if text:
                reconstruction.write_text(str(stage))
            else:
                reconstruction.write(str(stage))
            for f in stage.iterdir():
                with open(f, "rb+") as fh:
                    os.fsync(fh.fileno())
            back = pycolmap.Reconstruction(str(stage))
            counts = (back.num_cameras(), back.num_images(), back.num_points3D())
            if counts != (reconstruction.num_cameras(), reconstruction.num_images(), reconstruction.num_points3D()):
                raise RuntimeError("database or disk is full: the model read back differs")
        except (OSError, RuntimeError, ValueError, IndexError) as exc:
            if isinstance(exc, OSError) and not is_disk_full(exc):
                raise
            raise disk_full_error(folder.parent, f"writing the model {folder}") from None
        written = {f.name for f in stage.iterdir()}
        for f in sorted(stage.iterdir()):
            os.replace(f, folder / f.name)
        from .paths import MODEL_STEMS

        for stem in MODEL_STEMS:
            for ext in (".bin", ".txt"):
                if f"{stem}{ext}" not in written:
                    (folder / f"{stem}{ext}").unlink(missing_ok=True)
        _fsync_dir(folder)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        _WORKING_FILES.discard(stage)
    return folder


#: The lock file inside a :func:`private_tempdir`: held while its run lives.
_TEMPDIR_LOCK = ".colmap-miho.lock"


@contextlib.contextmanager
def private_tempdir(prefix: str, parent: str | os.PathLike | None = None):
    """A new temporary folder (``parent``, default ``$TMPDIR``) removed on exit, and also by
    the next run after a ``kill -9``: the folder holds a lock file locked (``flock``) while its
    run lives, and earlier folders of the same ``prefix`` whose lock nobody holds are removed
    first (only folders with that lock file: never a user's folder).

    Raises:
        RunFailed: disk full while creating it.
    """
    where = Path(parent) if parent is not None else Path(tempfile.gettempdir())
    _remove_stale_tempdirs(where, prefix)
    try:
        path = Path(tempfile.mkdtemp(prefix=prefix, dir=where))
        lock = open(path / _TEMPDIR_LOCK, "w")  # noqa: SIM115 - held open for the folder's life
    except OSError as exc:
        if is_disk_full(exc):
            raise disk_full_error(where, "creating a working folder") from None
        raise
    fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
    _WORKING_FILES.add(path)
    try:
        yield path
    finally:
        lock.close()
        shutil.rmtree(path, ignore_errors=True)
        _WORKING_FILES.discard(path)


def _remove_stale_tempdirs(parent: Path, prefix: str) -> None:
    with contextlib.suppress(OSError):
        for folder in parent.glob(f"{prefix}*"):
            lock_file = folder / _TEMPDIR_LOCK
            if not folder.is_dir() or not lock_file.is_file():
                continue
            try:
                fd = os.open(lock_file, os.O_RDWR)
            except OSError:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # a live run holds it
                continue
            finally:
                os.close(fd)
            shutil.rmtree(folder, ignore_errors=True)
            log.info("removed %s, left by an interrupted earlier run", folder)


def file_identity(path: Path) -> tuple:
    """What must not change under an in-place run: device, inode, size, mtime (ns) and the
    first 100 bytes (SQLite's header with its change counter)."""
    st = os.stat(path)
    with open(path, "rb") as fh:
        header = fh.read(100)
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, header


def default_output_path(database: Path) -> Path:
    """``<dir>/<stem>.miho.db`` beside the input."""
    return database.with_name(f"{database.stem}.miho{database.suffix or '.db'}")


def backup_path(database: Path, now: float | None = None) -> Path:
    """A timestamped backup name beside ``database`` that does not exist yet."""
    return _unused_stamped_name(database, lambda stamp: f"{database.name}.{stamp}.bak", now)


def _unused_stamped_name(database: Path, name_for, now: float | None = None) -> Path:
    """``database.with_name(name_for(stamp))`` with the local time as stamp, ``-1``, ``-2``, ...
    appended to the stamp until the name does not exist."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    candidate = database.with_name(name_for(stamp))
    k = 1
    while candidate.exists():
        candidate = database.with_name(name_for(f"{stamp}-{k}"))
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


#: Free space a refine run needs beside its output, in database sizes: the working copy, its
#: write-ahead log (up to the rewritten pages: about the copy again) and the run store of
#: filtered pairs and refined groups, with a margin over the peak measured on a small tmpfs
#: (``test_refine_fits_the_space_it_asks_for`` runs with exactly this much). A write that
#: still fills the disk ends with one line (see ``ColmapDatabase.transaction``).
WORKING_SPACE_FACTOR = 3.5
#: Free space on top of :data:`WORKING_SPACE_FACTOR`, bytes (SQLite's pages and the -shm file
#: of a small database).
WORKING_SPACE_MARGIN = 1 << 20


def working_space(size: int, *, in_place: bool = False) -> int:
    """Bytes of free space a run on a database of ``size`` bytes needs beside its output (in
    place: the backup too)."""
    return int((WORKING_SPACE_FACTOR + (1 if in_place else 0)) * size) + WORKING_SPACE_MARGIN


class WorkingCopy:
    """Plan and carry out the safe write of a processed database.

    Use as a context manager: ``path`` is a temporary copy of the input beside the output.
    Call :meth:`commit` after all writes (and after every database handle on ``path`` is
    closed) to move it onto the output. Leaving the block without commit, or with an
    exception, deletes the temporary copy (and, in place, the now useless backup); the input
    is never written.

    The checks made at the start are made again at commit time, right before the replace:
    an output that appeared meanwhile (another run) is not replaced without ``overwrite``; an
    output another SQLite client holds open is never replaced (SQLite would later apply that
    client's journal to the new file); in place, the input must be unchanged (device, inode,
    size, mtime and header), else the result is kept beside it under a visible name.

    Args:
        database: the input database (checked, not opened). In place on a symlink, the link's
            target is replaced and the link kept.
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
        self.overwrite = overwrite
        # in place on a symlink: replace the real file (beside it), keep the link
        if in_place:
            self.output = self.database.resolve()
        else:
            self.output = Path(output) if output else default_output_path(self.database)
        if not in_place:
            if self.output.resolve() == self.database.resolve() or _same_inode(self.output, self.database):
                raise UserError(f"output {self.output} is the input database; use --in-place to replace it")
            if self.output.is_dir():
                raise UserError(f"output {self.output} is a folder; give a database file name")
            if self.output.exists() and not overwrite:
                raise UserError(f"output {self.output} exists; pass --overwrite to replace it")
            if not self.output.parent.is_dir():
                raise UserError(f"output folder does not exist: {self.output.parent}")
            if self.output.exists():
                check_not_in_use(self.output)
        if not os.access(self.output.parent, os.W_OK | os.X_OK):
            raise UserError(f"cannot write in {self.output.parent} (read-only folder); "
                            + ("copy the database to a writable folder" if in_place else "choose another --output"))
        self.backup: Path | None = None
        self.path: Path | None = None
        self.committed = False
        self._identity: tuple | None = None
        self._side: list[tuple[Path, Path]] = []

    def __enter__(self) -> WorkingCopy:
        check_not_in_use(self.database)
        _warn_leftover_copies(self.output)
        size = self.database.stat().st_size
        check_free_space(self.output.parent, working_space(size, in_place=self.in_place),
                         f"refining {self.database}" + (" in place (with its backup)" if self.in_place else ""))
        self._identity = file_identity(self.output if self.in_place else self.database)
        if self.in_place:
            backup = backup_path(self.output)
            copy_file(self.database, backup)
            self.backup = backup
            _PENDING_BACKUPS[backup] = (self.output, self._identity)
            log.info("backup of the input written to %s", self.backup)
        try:
            fd, name = tempfile.mkstemp(prefix=f".{self.output.name}.", suffix=".tmp", dir=self.output.parent)
        except OSError as exc:
            self._drop_backup()
            raise UserError(f"cannot create a working copy in {self.output.parent}: {exc.strerror}") from None
        os.close(fd)
        self.path = Path(name)
        _WORKING_FILES.add(self.path)
        try:
            copy_file(self.database, self.path)
            check_integrity(self.path, self.database)
            # mkstemp makes the file private (0600): give the result the input's permissions
            os.chmod(self.path, stat.S_IMODE(self.database.stat().st_mode))
        except BaseException:
            remove_with_side_files(self.path)
            self._drop_backup()
            raise
        return self

    def stage_side_file(self, path: str | os.PathLike, text: str) -> None:
        """Write ``text`` now to a new hidden file beside ``path`` (flushed, size checked);
        :meth:`commit` renames it onto ``path`` right after the database (so a bad path fails
        before anything is replaced, and no side file describes a result that was not
        committed). A symlink ``path`` keeps its link: its target is replaced.

        Raises:
            UserError: the file cannot be written (missing or read-only folder, disk full).
        """
        target = write_target(path)
        data = text.encode("utf-8")
        try:
            tmp = _new_staging_name(target)
        except UserError as exc:
            raise UserError(f"{exc}; nothing was replaced") from None
        try:
            with open(tmp, "wb") as fh:
                fh.write(data)
            _check_written(tmp, target, len(data))
        except (OSError, UserError) as exc:
            tmp.unlink(missing_ok=True)
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise UserError(f"cannot write {target}: {why}; nothing was replaced") from None
        os.chmod(tmp, 0o666 & ~_umask())
        self._side.append((tmp, target))

    def commit(self) -> Path:
        """Check again, then atomically move the working copy onto the output; returns it.

        Raises:
            UserError: the output appeared meanwhile (no ``overwrite``), or is held open.
            DatabaseError: in place, the input changed during the run; the result is kept
                beside it (named in the message) and the input is left as it is.
        """
        if self.path is None:
            raise RuntimeError("commit() outside the with block")
        if self.in_place:
            self._check_input_unchanged()
            check_not_in_use(self.output)
        elif self.output.exists() or self.output.is_symlink():
            if not self.overwrite:
                raise UserError(f"output {self.output} was created by another program during the run; "
                                "nothing was replaced (pass --overwrite to replace it)")
            check_not_in_use(self.output)
        for s in SIDE_SUFFIXES:
            side = Path(str(self.path) + s)
            if side.exists():
                raise DatabaseError(f"working copy {self.path} is still open ({side.name} exists)")
        with open(self.path, "rb+") as fh:
            os.fsync(fh.fileno())
        if self.in_place or self.overwrite:
            os.replace(self.path, self.output)
        else:
            _rename_no_replace(self.path, self.output)
        _WORKING_FILES.discard(self.path)
        if self.backup is not None:
            _PENDING_BACKUPS.pop(self.backup, None)  # the replaced input lives on in it
        _fsync_dir(self.output.parent)
        self.committed = True
        for tmp, target in self._side:
            os.replace(tmp, target)
        self._side.clear()
        return self.output

    def _check_input_unchanged(self) -> None:
        if self.path is None:
            raise RuntimeError("no working copy to check against")
        try:
            now = file_identity(self.output)
        except OSError:
            now = None
        if now == self._identity:
            return
        kept = _visible_name(self.output)
        os.replace(self.path, kept)
        self.path = None
        raise DatabaseError(
            f"database {self.database} changed during the run (another program wrote it), so it "
            f"was not replaced; the result, made from its earlier state, is kept in {kept} and "
            f"that state in the backup {self.backup}: rerun on the database as it is now")

    def _drop_backup(self) -> None:
        """Delete the backup of an in-place run that replaced nothing (the input is as it was)."""
        if self.backup is None:
            return
        try:
            unchanged = file_identity(self.output) == self._identity
        except OSError:
            unchanged = False
        if unchanged:
            self.backup.unlink(missing_ok=True)
            _PENDING_BACKUPS.pop(self.backup, None)
            self.backup = None

    def __exit__(self, exc_type, exc, tb) -> None:
        for tmp, _ in self._side:
            tmp.unlink(missing_ok=True)
        if not self.committed and self.path is not None:  # None: kept beside a changed input
            remove_with_side_files(self.path)
            _WORKING_FILES.discard(self.path)
            self._drop_backup()
        if isinstance(exc, (RuntimeError, sqlite3.Error)) and is_disk_full(exc):
            # pycolmap's "database or disk is full" (a RuntimeError): a known condition, one line
            raise RunFailed(f"disk full while writing in {self.output.parent}; {self.database} is unchanged and "
                            "the working files were removed: free some space and retry") from None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _same_inode(a: Path, b: Path) -> bool:
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        return False
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def _visible_name(database: Path) -> Path:
    """``<stem>.miho-<time>.db`` beside ``database``, not existing yet."""
    return _unused_stamped_name(database, lambda stamp: f"{database.stem}.miho-{stamp}{database.suffix or '.db'}")


def publish_new_file(src: Path, dst: Path) -> None:
    """Move the finished, closed file ``src`` onto the NEW name ``dst`` (flushed first): only
    if nothing appeared at ``dst`` meanwhile (another run), atomically where hard links work.

    Raises:
        UserError: ``dst`` exists.
    """
    with open(src, "rb+") as fh:
        os.fsync(fh.fileno())
    _rename_no_replace(src, dst)
    _fsync_dir(dst.parent)


def _rename_no_replace(src: Path, dst: Path) -> None:
    """Move ``src`` to ``dst`` only if ``dst`` does not exist, atomically where the file
    system supports hard links (a race with another run cannot replace its result).

    Raises:
        UserError: ``dst`` exists.
    """
    try:
        os.link(src, dst)
    except FileExistsError:
        raise UserError(f"output {dst} was created by another program during the run; nothing "
                        "was replaced (pass --overwrite to replace it)") from None
    except OSError:  # no hard links here (some network/FAT file systems): check, then rename
        if dst.exists():
            raise UserError(f"output {dst} was created by another program during the run; nothing "
                            "was replaced (pass --overwrite to replace it)") from None
        os.replace(src, dst)
        return
    src.unlink()


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

