"""COLMAP's own log (glog) sent to a file instead of the terminal, for every pycolmap call that maps or extracts."""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

#: Lines of a replayed log that are never shown: glog's file header.
_NOT_REPLAYED = ("Log file created at:", "Running on machine:", "Running duration (h:mm:ss):",
                 "Log line format:")
#: The global mapper's warning for every image, which it is not given on purpose (only the
#: colours of its points would come from them): hidden from its replayed log by default.
MAPPER_IMAGE_WARNING = "Could not read image"


#: The start of a glog record: severity, date, time, thread id, source file and line.
_GLOG_RECORD = re.compile(r"[IWEF]\d{8} \d{2}:\d{2}:\d{2}\.\d{6} +\d+ [^\s\]]+:\d+\] ")


@contextlib.contextmanager
def colmap_log_to_file(folder: Path | None, *, verbose: bool = False, errors_to_terminal: bool = True,
                       replay: bool = False, hide: tuple[str, ...] = (MAPPER_IMAGE_WARNING,)):
    """Send COLMAP's glog output to ``folder/colmap_log.<timestamp>`` (errors also to stderr unless
    ``errors_to_terminal`` is False); yields the path prefix, or None when verbose.

    With ``verbose`` and ``replay`` the lines reach stderr when the call ends, escaped (glog prints
    image names raw: a newline or ESC could forge a line), without records holding ``hide``. glog
    settings are process-wide and restored on exit."""
    import pycolmap

    lg = pycolmap.logging
    if (verbose and not replay) or folder is None:
        with glog_to_stderr():
            yield None
        return
    if verbose:  # replayed: the file gets everything, the terminal nothing until the end
        errors_to_terminal = False
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
        if verbose:
            replay_log(latest_log(prefix), hide)


def replay_log(log_file: Path | None, hide: tuple[str, ...] = (MAPPER_IMAGE_WARNING,)) -> None:
    """Write ``log_file``'s lines to stderr, escaped, without glog's header or records holding ``hide``."""
    import sys

    from ..terminal import printable

    if log_file is None:
        return
    try:
        text = log_file.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return
    records: list[str] = []
    for line in text.split("\n"):
        if records and not _GLOG_RECORD.match(line) and records[-1] and _GLOG_RECORD.match(records[-1]):
            records[-1] += "\n" + line  # a name with a newline: the rest of the same record
        else:
            records.append(line)
    skip = (*_NOT_REPLAYED, *hide)
    lines = [printable(r.rstrip("\n")) for r in records if r and not any(t in r for t in skip)]
    if lines:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.write("\n".join(lines) + "\n")
            sys.stderr.flush()


@contextlib.contextmanager
def glog_to_stderr():
    """COLMAP's log on stderr only for the block (glog otherwise leaves its own files in ``$TMPDIR``)."""
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


#: A step the global mapper times in its log ("Global positioning done in 1.03 seconds").
_STEP_DONE = re.compile(r"\] (.+?) done in ([0-9.eE+-]+) seconds")


def step_seconds(log_file: Path | None) -> dict[str, float]:
    """Seconds of each step a COLMAP log says it finished (lower case, last of repeats); empty without a file."""
    if log_file is None:
        return {}
    try:
        text = log_file.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return {}
    steps = {name.strip().lower(): float(sec) for name, sec in _STEP_DONE.findall(text)}
    steps.pop("reconstruction", None)
    return steps


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
