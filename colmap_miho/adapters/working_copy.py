"""The working copy of a user's database: every stage works on a private copy beside the output,
and only the commit publishes it (a new file, or an atomic replace of the input with a backup
when in place). A crash, Ctrl-C or kill at any moment leaves the input as it was."""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

from ..errors import DatabaseError, RunFailed, UserError
from .filesystem import WORKING_FILES, current_umask, fsync_dir, fsync_file, temp_beside
from .safety import (
    PENDING_BACKUPS,
    SIDE_SUFFIXES,
    backup_path,
    check_free_space,
    check_integrity,
    check_not_in_use,
    copy_file,
    default_output_path,
    file_identity,
    locked_by_other_process,
    remove_with_side_files,
    side_files,
    unused_stamped_name,
)
from .staged_write import (
    CHARACTER_DEVICE,
    check_output_path,
    check_written,
    device_full_error,
    disk_full_error,
    file_too_large,
    is_disk_full,
    new_staging_name,
    write_target,
)

log = logging.getLogger(__name__)

#: What to do about an existing output, for the CLI and for Python callers alike.
OVERWRITE_ADVICE = "pass --overwrite (overwrite=True in Python) to replace it"

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
    """Bytes of free space a run on a database of ``size`` bytes needs beside its output (in place: the backup too)."""
    return int((WORKING_SPACE_FACTOR + (1 if in_place else 0)) * size) + WORKING_SPACE_MARGIN


class WorkingCopy:
    """Plan and carry out the safe write of a processed database: ``path`` is a temporary copy
    beside the output, moved onto it by :meth:`commit` after the start's checks are repeated;
    leaving without commit deletes it. ``in_place`` replaces the input after a timestamped backup.
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
            check_output_path(self.output, "--output", device=False)  # a FIFO, a device: never replaced
            if self.output.exists() and not overwrite:
                raise UserError(f"output {self.output} exists; {OVERWRITE_ADVICE}")
            if self.output.is_symlink() and not self.output.exists():  # would read "created meanwhile" at the end
                raise UserError(f"output {self.output} is a symlink to {os.readlink(self.output)}, which does not "
                                "exist; remove the link or choose another --output")
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
        self._devices: list[tuple[bytes, Path]] = []  # what is written through a character device

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
            PENDING_BACKUPS[backup] = (self.output, self._identity)
            log.info("backup of the input written to %s", self.backup)
        try:
            self.path = temp_beside(self.output)
        except OSError as exc:
            self._drop_backup()
            raise UserError(f"cannot create a working copy in {self.output.parent}: {exc.strerror}") from None
        WORKING_FILES.add(self.path)
        try:
            copy_file(self.database, self.path)
            _refuse_side_files(self.path)  # before SQLite first opens it (and makes its own)
            check_integrity(self.path, self.database)
            # mkstemp makes the file private (0600): give the result the input's permissions
            os.chmod(self.path, stat.S_IMODE(self.database.stat().st_mode))
        except _ForeignSideFile:
            self.path.unlink(missing_ok=True)  # not the side file: it is not ours
            WORKING_FILES.discard(self.path)
            self._drop_backup()
            raise
        except BaseException:
            remove_with_side_files(self.path)
            self._drop_backup()
            raise
        return self

    def stage_side_file(self, path: str | os.PathLike, text: str) -> None:
        """Stage ``text`` for ``path`` now (so a bad path fails early); :meth:`commit` puts it
        in place right after the database. A character device is written through at commit,
        its text held in memory. UserError when it cannot be written or is no regular file."""
        data = text.encode("utf-8")
        if check_output_path(path) == CHARACTER_DEVICE:  # a FIFO, a socket ...: refused here
            # kept in memory, written through at commit: no file of ours anywhere meanwhile (one
            # staged in $TMPDIR outlived a kill -9, and nothing would ever remove it)
            self._devices.append((data, Path(path)))
            return
        target = write_target(path)
        try:
            tmp = new_staging_name(target)
        except UserError as exc:
            raise UserError(f"{exc}; nothing was replaced") from None
        try:
            with open(tmp, "wb") as fh:
                fh.write(data)
            check_written(tmp, target, len(data))
        except (OSError, UserError) as exc:
            tmp.unlink(missing_ok=True)
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise UserError(f"cannot write {target}: {why}; nothing was replaced") from None
        os.chmod(tmp, 0o666 & ~current_umask())
        self._side.append((tmp, target))

    def commit(self) -> Path:
        """Check again, then move the working copy onto the output atomically; returns it. UserError,
        DatabaseError (in place, the input changed) or SideFileLost."""
        if self.path is None:
            raise RuntimeError("commit() outside the with block")
        if self.in_place:
            self._check_input_unchanged()
            check_not_in_use(self.output)
        elif self.output.exists() or self.output.is_symlink():
            check_output_path(self.output, "--output", device=False)  # it may have become a FIFO meanwhile
            if not self.overwrite:
                raise UserError(f"output {self.output} was created by another program during the run; "
                                "nothing was replaced (pass --overwrite (overwrite=True in Python) to replace it)")
            check_not_in_use(self.output)
        for s in SIDE_SUFFIXES:
            side = Path(str(self.path) + s)
            if side.exists():
                raise DatabaseError(f"working copy {self.path} is still open ({side.name} exists)")
        self._write_devices()
        fsync_file(self.path)
        if self.in_place or self.overwrite:
            os.replace(self.path, self.output)
        else:
            _rename_no_replace(self.path, self.output)
        WORKING_FILES.discard(self.path)
        if self.backup is not None:
            PENDING_BACKUPS.pop(self.backup, None)  # the replaced input lives on in it
        fsync_dir(self.output.parent)
        self.committed = True
        for tmp, target in self._side:
            try:
                os.replace(tmp, target)
            except OSError as exc:  # the one step after the commit: the output is there
                raise SideFileLost(f"{self.output} was written, but {target} could not be "
                                   f"({exc.strerror or exc}); the output is complete: rerun with --overwrite "
                                   "to write both again") from None
        self._side.clear()
        return self.output

    def _write_devices(self) -> None:
        """Write the text staged for a character device into it (RunFailed when full)."""
        for data, target in list(self._devices):
            if check_output_path(target) != CHARACTER_DEVICE:  # looked at again: a FIFO is refused there
                raise UserError(f"{target} changed from a character device to a file during the run; nothing was "
                                "replaced: run again")
            try:
                with open(target, "wb") as fh:
                    fh.write(data)
            except OSError as exc:
                if is_disk_full(exc):
                    raise device_full_error(target, exc) from None
                raise UserError(f"cannot write {target}: {exc.strerror or exc}; nothing was replaced") from None
            self._devices.remove((data, target))

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
        if self.backup is None:
            return
        try:
            unchanged = file_identity(self.output) == self._identity
        except OSError:
            unchanged = False
        if unchanged:
            self.backup.unlink(missing_ok=True)
            PENDING_BACKUPS.pop(self.backup, None)
            self.backup = None

    def __exit__(self, exc_type, exc, tb) -> None:
        for tmp, _ in self._side:
            tmp.unlink(missing_ok=True)
        if not self.committed and self.path is not None:  # None: kept beside a changed input
            remove_with_side_files(self.path)
            WORKING_FILES.discard(self.path)
            self._drop_backup()
        if exc is not None and is_disk_full(exc):
            if file_too_large(self.output.parent, exc):  # ulimit -f: the one message it has everywhere
                raise disk_full_error(self.output.parent, f"refining {self.database} (unchanged)", exc) from None
            # ENOSPC / EDQUOT, SQLite's or pycolmap's "database or disk is full": one line
            raise RunFailed(f"disk full while writing in {self.output.parent}; {self.database} is unchanged and "
                            "the working files were removed: free some space and retry") from None


class _ForeignSideFile(UserError):
    """A -wal, -shm or -journal file appeared beside a new working copy before SQLite opened it."""


def _refuse_side_files(path: Path) -> None:
    """Refuse a new working copy with an SQLite side file beside it (a link planted during the copy
    would take SQLite's journal)."""
    for suffix in SIDE_SUFFIXES:
        side = Path(str(path) + suffix)
        if os.path.lexists(side):
            what = f"a symbolic link (to {os.readlink(side)})" if side.is_symlink() else "a file"
            raise _ForeignSideFile(f"{side} appeared beside the working copy while it was made, {what} that "
                                   "colmap-miho did not make; SQLite would write through it, so nothing was: "
                                   f"remove it (and see who writes in {path.parent}), then run again")


class SideFileLost(RunFailed):
    """The output was committed, but a side file (``--json``) could not be put in place after it."""


def _same_inode(a: Path, b: Path) -> bool:
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        return False
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def _visible_name(database: Path) -> Path:
    return unused_stamped_name(database, lambda stamp: f"{database.stem}.miho-{stamp}{database.suffix or '.db'}")


def publish_new_file(src: Path, dst: Path, *, advice: str = OVERWRITE_ADVICE) -> None:
    """Move the closed file ``src`` onto the NEW name ``dst``, only if nothing appeared there
    (UserError, ending with ``advice``)."""
    fsync_file(src)
    _rename_no_replace(src, dst, advice=advice)
    fsync_dir(dst.parent)


def _rename_no_replace(src: Path, dst: Path, *, advice: str = OVERWRITE_ADVICE) -> None:
    """Move ``src`` to ``dst`` only if ``dst`` does not exist, atomically where hard links work."""
    try:
        os.link(src, dst)
    except FileExistsError:
        raise UserError(f"output {dst} was created by another program during the run; nothing "
                        f"was replaced ({advice})") from None
    except OSError:  # no hard links here (some network/FAT file systems): check, then rename
        if dst.exists():
            raise UserError(f"output {dst} was created by another program during the run; nothing "
                            f"was replaced ({advice})") from None
        os.replace(src, dst)
        return
    src.unlink()


def leftover_copies(output: Path) -> list[Path]:
    """Hidden working copies of ``output`` left by killed runs, oldest first (open ones excluded)."""
    found = [f for f in Path(output).parent.glob(f".{Path(output).name}.*.tmp")
             if f.is_file() and not locked_by_other_process(f)]
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
