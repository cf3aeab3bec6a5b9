"""Writing a user-visible file whole or not at all (:func:`staged_write`), telling a full disk from
other errors, and private temporary folders swept after a kill."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import shutil
import sqlite3
import stat
import tempfile
import time
from pathlib import Path

from ..errors import RunFailed, UserError
from .filesystem import (
    WORKING_FILES,
    current_umask,
    fsync_dir,
    fsync_file,
    remove_own_file,
    replace_durably,
    temp_beside,
)
from .model_files import MODEL_EXTENSIONS, MODEL_STEMS

log = logging.getLogger(__name__)

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


#: What SQLite (through pycolmap's RuntimeError) says when the disk is full.
SQLITE_FULL_TEXT = ("database or disk is full", "disk i/o error", "no space left on device")


def is_disk_full(exc: BaseException) -> bool:
    """True for a full disk: ENOSPC / EDQUOT / EFBIG, ``SQLITE_FULL``, pycolmap's "database or disk is full"."""
    if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
        return True
    if isinstance(exc, (OSError, RuntimeError, sqlite3.Error)):  # h5py's OSError carries no errno
        text = str(exc).lower()
        return any(t in text for t in SQLITE_FULL_TEXT)
    return False


#: Below this many free bytes a file system counts as full when a native writer fails
#: without saying why (:func:`out_of_room`).
MIN_ROOM_BYTES = 1 << 20


def out_of_room(folder: str | os.PathLike) -> bool:
    """Whether ``folder``'s file system is full (space or inodes); False when it cannot be read."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < MIN_ROOM_BYTES or (st.f_files > 0 and st.f_favail == 0)


def file_size_limit() -> int | None:
    """The largest file this process may write in bytes (``ulimit -f``), or None when unlimited."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return None
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


def file_too_large(folder: str | os.PathLike, exc: BaseException | None = None) -> bool:
    """Whether a failed write in ``folder`` met a file-size limit rather than a full disk."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return False
    if isinstance(exc, OSError) and exc.errno == errno.EFBIG:
        return True
    return file_size_limit() is not None and not out_of_room(folder)


def disk_full_error(folder: Path, what: str, exc: BaseException | None = None) -> RunFailed:
    """The one-line error of a full disk or a file-size limit, naming the folder and what was kept."""
    if file_too_large(folder, exc):
        limit = file_size_limit()
        why, fix = ((f"this process writes files of at most {limit / 1e6:.1f} MB (ulimit -f)",
                     "raise that limit (ulimit -f unlimited) and retry") if limit is not None else
                    (f"the file system of {folder} takes no file this large", "write elsewhere"))
        return RunFailed(f"file too large in {folder} while {what}: {why}; nothing was written under the output "
                         f"name and the working files were removed: {fix}")
    free = ""
    with contextlib.suppress(OSError):
        free = f" ({shutil.disk_usage(folder).free / 1e6:.1f} MB free)"
        st = os.statvfs(folder)
        if st.f_files > 0 and st.f_favail == 0:
            free = " (no free inode: too many files)"
    return RunFailed(f"disk full in {folder}{free} while {what}; nothing was written under the output name "
                     "and the working files were removed: free some space and retry")


def device_full_error(device: str | os.PathLike, exc: OSError) -> RunFailed:
    """The one line for a full character device (``/dev/full``), which has no folder to name."""
    return RunFailed(f"disk full while writing {device} ({exc.strerror or exc}); nothing was written under the "
                     "output name and the working files were removed: write it elsewhere or retry")


def write_target(path: str | os.PathLike) -> Path:
    """The file writing ``path`` replaces: a symlink's target (the link is kept), else ``path``."""
    p = Path(path)
    return p.resolve() if p.is_symlink() else p


#: What a path that is not a regular file is, by its ``st_mode`` test (for the messages).
_KINDS = ((stat.S_ISDIR, "folder"), (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
          (stat.S_ISFIFO, "FIFO (named pipe)"), (stat.S_ISSOCK, "socket"))

#: The kind of target a file output writes through instead of replacing.
CHARACTER_DEVICE = "character device"


def output_kind(path: str | os.PathLike) -> str | None:
    """What writing ``path`` would meet: None for nothing or a regular file, else its kind in words."""
    try:
        mode = os.stat(path).st_mode
    except OSError:  # missing (or unreachable: the write itself then says why)
        return None
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in _KINDS if test(mode)), "special file")


def check_output_path(path: str | os.PathLike, label: str | None = None, *, device: bool = True) -> str | None:
    """Refuse, before any work, an output ``path`` that is a FIFO, socket, block device or folder,
    and a character device unless ``device``. Returns :func:`output_kind`; UserError names
    ``label``."""
    kind = output_kind(path)
    if kind is None or (kind == CHARACTER_DEVICE and device):
        return kind
    what = f"{label} {path}" if label else str(path)
    if kind == "folder":
        raise UserError(f"{what} is a folder; give a file name")
    raise UserError(f"{what} is a {kind}, not a regular file: only a regular file (or a new name) is "
                    "written; give a file name")


def write_through(tmp: Path, device: str | os.PathLike) -> None:
    """Copy the finished staged file ``tmp`` into the character device ``device``."""
    with open(tmp, "rb") as src, open(device, "wb") as dst:
        shutil.copyfileobj(src, dst)


def new_staging_name(target: Path) -> Path:
    """:func:`~colmap_miho.adapters.filesystem.temp_beside` with its failures told in one line."""
    try:
        return temp_beside(target)
    except FileNotFoundError:
        raise UserError(f"cannot write {target}: its folder {target.parent} does not exist") from None
    except OSError as exc:
        if is_disk_full(exc):
            raise disk_full_error(target.parent, f"writing {target}", exc) from None
        raise UserError(f"cannot write {target}: {exc.strerror or exc}") from None


def check_written(tmp: Path, target: Path, expected_size: int | None) -> None:
    """Flush ``tmp`` and check its size (a native writer on a full disk often leaves a short file
    silently); RunFailed when it differs."""
    size = fsync_file(tmp)
    if (size != expected_size) if expected_size is not None else size == 0:
        want = f"{expected_size} bytes expected" if expected_size is not None else "an empty file"
        raise disk_full_error(target.parent, f"writing {target} ({size} bytes written, {want})")


@contextlib.contextmanager
def staged_write(path: str | os.PathLike, *, expected_size=None):
    """Write one output file whole or not at all: yields a hidden file beside the target to fill,
    then flushes, checks its size (``expected_size``) and renames it, or removes it on failure.
    RunFailed for a full disk or short write; UserError for a bad folder or target."""
    check_output_path(path)
    if output_kind(path) == CHARACTER_DEVICE:
        # staged in a folder of our own in $TMPDIR (/dev is not writable by everyone), which the
        # next run removes should a kill -9 leave it
        with private_tempdir(DEVICE_STAGING_PREFIX, own_failures=False) as folder:
            with _staged(path, folder / Path(path).name, True, expected_size) as tmp:
                yield tmp
        return
    with _staged(path, write_target(path), False, expected_size) as tmp:
        yield tmp


@contextlib.contextmanager
def _staged(path: str | os.PathLike, target: Path, device: bool, expected_size):
    """:func:`staged_write` onto ``target`` (``device``: writing through into ``path``)."""
    tmp = new_staging_name(target)
    WORKING_FILES.add(tmp)
    try:
        try:
            yield tmp
            try:
                expected = expected_size(tmp) if callable(expected_size) else expected_size
            except ValueError as exc:  # no readable header: cut short
                raise disk_full_error(target.parent, f"writing {target} ({exc})") from None
            check_written(tmp, target, expected)
            if check_output_path(path) == CHARACTER_DEVICE:  # looked at again: it may have changed
                try:
                    write_through(tmp, path)
                except OSError as exc:
                    if is_disk_full(exc):  # the device's, not the staging folder's
                        raise device_full_error(path, exc) from None
                    raise
                return
            if device:
                raise UserError(f"{path} changed from a character device to a file during the run; nothing "
                                "was written: run again")
            os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes it private
            replace_durably(tmp, target)
        except (OSError, RuntimeError) as exc:
            if is_disk_full(exc):
                raise disk_full_error(target.parent, f"writing {target}", exc) from None
            raise
    finally:
        with contextlib.suppress(OSError):
            remove_own_file(tmp)
        WORKING_FILES.discard(tmp)


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
    """The size a binary PLY file must have by its own header; ValueError when it has none."""
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
    """Write a reconstruction into ``folder`` via a hidden folder that is read back and checked,
    then renamed in; the other format's model files are removed. RunFailed leaves ``folder`` as it
    was."""
    import pycolmap

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        stage = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    except OSError as exc:
        if is_disk_full(exc):
            raise disk_full_error(folder.parent, f"writing the model {folder}") from None
        raise
    WORKING_FILES.add(stage)
    try:
        try:
            if text:
                reconstruction.write_text(str(stage))
            else:
                reconstruction.write(str(stage))
            for f in stage.iterdir():
                fsync_file(f)
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
        for stem in MODEL_STEMS:
            for ext in MODEL_EXTENSIONS:
                if f"{stem}{ext}" not in written:
                    remove_own_file(folder / f"{stem}{ext}")  # a link there is left as it is
        fsync_dir(folder)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        WORKING_FILES.discard(stage)
    return folder


#: The lock file inside a :func:`private_tempdir`: held while its run lives.
_TEMPDIR_LOCK = ".colmap-miho.lock"
#: The lock file's name before it is locked and renamed to :data:`_TEMPDIR_LOCK`.
_PENDING_LOCK = ".colmap-miho.pending-"
#: Seconds after which a folder whose lock file never appeared (its run was killed in the
#: moment between making the folder and locking it) is removed by a sweep.
PENDING_TEMPDIR_S = 60.0


@contextlib.contextmanager
def private_tempdir(prefix: str, parent: str | os.PathLike | None = None, *, own_failures: bool = True):
    """A new temporary folder removed on exit, and by the next run after a ``kill -9`` (its lock
    file is held while it lives; free ones are swept). ``own_failures``: errors while its disk is
    full become the full-disk error."""
    where = Path(parent) if parent is not None else Path(tempfile.gettempdir())
    _remove_stale_tempdirs(where, prefix)
    try:
        path = Path(tempfile.mkdtemp(prefix=prefix, dir=where))
        fd, pending = tempfile.mkstemp(prefix=_PENDING_LOCK, dir=path)
    except OSError as exc:
        if is_disk_full(exc):
            raise disk_full_error(where, "creating a working folder", exc) from None
        raise
    WORKING_FILES.add(path)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.rename(pending, path / _TEMPDIR_LOCK)  # visible only once locked
        yield path
    except (OSError, RuntimeError, ValueError, sqlite3.Error) as exc:
        # a native writer (SQLite, COLMAP) that fails on a full file system rarely says so
        # ("No registered database factory succeeded"): its state, read before the folder is
        # removed, tells
        if not own_failures or isinstance(exc, UserError) or not (is_disk_full(exc) or out_of_room(path)):
            raise
        room = "" if parent is not None else " (or set TMPDIR to a folder with room)"
        raise disk_full_error(where, f"working in a temporary folder there ({path.name}){room}", exc) from exc
    finally:
        shutil.rmtree(path, ignore_errors=True)  # still locked: no sweep takes it meanwhile
        os.close(fd)
        WORKING_FILES.discard(path)


#: The folder in which :func:`staged_write` stages a file written through into a character device.
DEVICE_STAGING_PREFIX = "colmap_miho_device_"
#: The prefixes of the folders this package makes in ``$TMPDIR`` with :func:`private_tempdir`
#: (the map and import folders go beside their output instead).
TMPDIR_PREFIXES = (DEVICE_STAGING_PREFIX, "miho-global-", "colmap_miho_check_", "colmap_miho_report_",
                   "colmap_miho_cmp_", "colmap-miho-export-", "miho-mp-", "colmap_miho_dask_")


def sweep_stale_tempdirs(parent: str | os.PathLike | None = None) -> None:
    """Remove the folders killed runs left in ``parent`` under :data:`TMPDIR_PREFIXES`; never fails."""
    where = Path(parent) if parent is not None else Path(tempfile.gettempdir())
    for prefix in TMPDIR_PREFIXES:
        with contextlib.suppress(OSError):
            _remove_stale_tempdirs(where, prefix)


def _lock_is_free(lock_file: Path) -> bool:
    try:
        fd = os.open(lock_file, os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # a live run holds it
        return False
    finally:
        os.close(fd)
    return True


def _is_stale(folder: Path) -> bool:
    """A :func:`private_tempdir` folder whose run is gone (free lock, or a stale pending one)."""
    if not folder.is_dir() or folder.is_symlink():
        return False
    lock_file = folder / _TEMPDIR_LOCK
    if lock_file.is_file():
        return _lock_is_free(lock_file)
    entries = list(folder.iterdir())
    if not entries or not all(e.name.startswith(_PENDING_LOCK) and e.is_file() for e in entries):
        return False
    return (time.time() - folder.stat().st_mtime > PENDING_TEMPDIR_S
            and all(_lock_is_free(e) for e in entries))


def _remove_stale_tempdirs(parent: Path, prefix: str) -> None:
    with contextlib.suppress(OSError):
        for folder in parent.glob(f"{prefix}*"):
            try:
                stale = _is_stale(folder)
            except OSError:
                continue
            if stale:
                shutil.rmtree(folder, ignore_errors=True)
                log.info("removed %s, left by an interrupted earlier run", folder)
