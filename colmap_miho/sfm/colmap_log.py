"""COLMAP's own log (glog) sent to a file instead of the terminal, for every pycolmap call that
maps or extracts."""

from __future__ import annotations

import contextlib
from pathlib import Path


@contextlib.contextmanager
def colmap_log_to_file(folder: Path | None, *, verbose: bool = False, errors_to_terminal: bool = True):
    """Send COLMAP's glog output to ``folder/colmap_log.<timestamp>``; its errors also reach
    stderr unless ``errors_to_terminal`` is False (a call whose failure the caller reports in
    its own words).

    Yields the log file's path prefix (glog appends a timestamp), or None when verbose (or
    ``folder`` is None): then COLMAP's log goes to stderr only (see :func:`glog_to_stderr`),
    never to glog's own files in ``$TMPDIR``. glog settings are process-wide; they are
    restored on exit.
    """
    import pycolmap

    lg = pycolmap.logging
    if verbose or folder is None:
        with glog_to_stderr():
            yield None
        return
    saved = (lg.logtostderr, lg.alsologtostderr, lg.stderrthreshold, lg.minloglevel)
    prefix = Path(folder) / "colmap_log."
    try:
        lg.minloglevel = 0  # the file gets everything, even when the caller silenced COLMAP
        lg.logtostderr = False
        lg.alsologtostderr = False
        lg.stderrthreshold = 2 if errors_to_terminal else 3  # ERROR (unless the caller reports it) and FATAL
        lg.set_log_destination(lg.INFO, str(prefix))
        lg.set_log_destination(lg.WARNING, "")  # warnings are in the INFO file already
        lg.set_log_destination(lg.ERROR, "")
        yield prefix
    finally:
        lg.logtostderr, lg.alsologtostderr, lg.stderrthreshold, lg.minloglevel = saved
        lg.set_log_destination(lg.INFO, "")


@contextlib.contextmanager
def glog_to_stderr():
    """COLMAP's log (glog) on stderr only for the block, restored after: by default glog also
    writes every line into files of its own in ``$TMPDIR`` (``.<host>.<user>.log.INFO.<time>.<pid>``,
    ``.WARNING``, ``.ERROR``) that nobody asked for and nobody removes. Which lines reach
    stderr is still ``minloglevel``'s to say."""
    import pycolmap

    lg = pycolmap.logging
    saved = lg.logtostderr
    lg.logtostderr = True
    try:
        yield
    finally:
        lg.logtostderr = saved


def latest_log(prefix: Path | None) -> Path | None:
    """The newest log file glog wrote under ``prefix`` (None when verbose or none)."""
    if prefix is None:
        return None
    found = sorted(prefix.parent.glob(prefix.name + "*"), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else None


def last_error_line(log_file: Path | None) -> str:
    """The message of the last error (``E...``) line of a glog file, "" when none (or no file)."""
    if log_file is None:
        return ""
    try:
        lines = log_file.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return ""
    for line in reversed(lines):
        if line.startswith(("E", "F")) and "] " in line:
            return line.split("] ", 1)[1].strip()
    return ""
