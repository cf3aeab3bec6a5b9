"""The ``colmap-miho`` command line: one console script, a module per subcommand (``commands/``)
with heavy imports inside ``run``. Failures are one line and an exit code (2 user error, 1 failed
run, 130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import pkgutil
import signal
import socket
import sqlite3
import sys
import threading

from .errors import Terminated, UserError
from .terminal import PrintableFormatter, printable
from .version import __version__

log = logging.getLogger("colmap_miho")


def _command_modules() -> list:
    from . import commands

    mods = []
    for info in pkgutil.iter_modules(commands.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(mod, "run") and hasattr(mod, "add_arguments"):
            mods.append(mod)
    return sorted(mods, key=lambda m: (getattr(m, "ORDER", 100), m.__name__))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="colmap-miho",
        description=(
            "Filter (MOP+MiHo) and refine (track-consistent NCC, then least-squares matching) the "
            "matches of a COLMAP database before Structure-from-Motion, then map and evaluate."
        ),
    )
    parser.add_argument("--version", action="version", version=f"colmap-miho {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        name = mod.__name__.rsplit(".", 1)[1].rstrip("_").replace("_", "-")
        name = getattr(mod, "NAME", name)
        p = sub.add_parser(name, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        verbosity = p.add_mutually_exclusive_group()
        verbosity.add_argument("-v", "--verbose", action="store_true", help="more log output (and COLMAP's own log)")
        verbosity.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors, no progress bars")
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run, _paths=getattr(mod, "paths", None))
    return parser


def configure_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    # names read from files reach the messages: their control characters are escaped (see .terminal)
    handler.setFormatter(PrintableFormatter("%(asctime)s %(name)s %(levelname)s: %(message)s" if verbose
                                            else "%(levelname)s: %(message)s"))
    root = logging.getLogger("colmap_miho")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


#: Seconds a SIGTERM or Ctrl-C may wait for the interpreter (held by a long COLMAP call, e.g.
#: mapping) before the working files are removed and the process exits anyway.
TERM_GRACE_S = 5.0
#: Seconds the clean-up after a SIGTERM that Python did serve (the working files, a Dask
#: cluster's shutdown) may take before the watcher removes the working files and exits anyway.
TERM_CLEANUP_S = 60.0


#: Exit status and what the exit says, per signal (SIGHUP: the terminal closed, ssh dropped).
_FORCED_EXITS = {signal.SIGTERM: (143, "terminated (SIGTERM)"), signal.SIGINT: (130, "interrupted")}
if hasattr(signal, "SIGHUP"):
    _FORCED_EXITS[signal.SIGHUP] = (129, "hung up (SIGHUP)")
#: The signals whose handler raises :class:`~colmap_miho.errors.Terminated`.
_TERMINATING = tuple(s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s is not None)


#: Set when the interpreter ran a SIGTERM / SIGINT handler: it is cleaning up on its own, and
#: the forced exit (for a signal held up by a long C++ call) is not needed.
_SIGNAL_HANDLED = threading.Event()


def _raise_terminated(signum, frame) -> None:
    _SIGNAL_HANDLED.set()
    exc = Terminated(f"terminated by signal {signum}")
    exc.signum = signum
    raise exc


def _raise_interrupted(signum, frame) -> None:
    _SIGNAL_HANDLED.set()
    raise KeyboardInterrupt


@contextlib.contextmanager
def _forced_exit_after_sigterm():
    """A signal during a long C++ call (the global mapper) would wait for it: a watcher thread gives
    the handler :data:`TERM_GRACE_S`, then removes the working files and exits itself."""
    rsock, wsock = socket.socketpair()
    wsock.setblocking(False)
    try:
        old_fd = signal.set_wakeup_fd(wsock.fileno(), warn_on_full_buffer=False)
    except ValueError:  # not the main thread
        rsock.close()
        wsock.close()
        yield
        return

    ended = threading.Event()  # the command returned: nothing left to force

    def watch() -> None:
        while True:
            try:
                data = rsock.recv(64)
            except OSError:
                return
            if not data:
                return
            signum = next((int(b) for b in data if int(b) in _FORCED_EXITS), None)
            if signum is None:
                continue
            if not _SIGNAL_HANDLED.wait(TERM_GRACE_S) and not ended.is_set():
                _forced_exit(signum, "during a COLMAP call")  # the handler never ran: a C++ call holds it
            if not ended.wait(TERM_CLEANUP_S):
                _forced_exit(signum, f"and the clean-up did not end within {TERM_CLEANUP_S:.0f} s")
            return

    thread = threading.Thread(target=watch, name="sigterm-watch", daemon=True)
    thread.start()
    try:
        yield
    finally:
        ended.set()
        signal.set_wakeup_fd(old_fd)
        wsock.close()
        with contextlib.suppress(OSError):
            rsock.shutdown(socket.SHUT_RDWR)
        thread.join(timeout=1)
        rsock.close()


def _forced_exit(signum: int, when: str) -> None:
    """Remove the working files and exit at once, with the line the interpreter would have printed."""
    import multiprocessing.process
    import shutil

    from .adapters.safety import exit_notes, remove_working_files

    notes = exit_notes()  # before the files go: a note may look at them
    remove_working_files()
    _stop_children()
    _release_semaphores()
    pool_tmp = multiprocessing.process.current_process()._config.get("tempdir")  # type: ignore[attr-defined]
    if pool_tmp:
        shutil.rmtree(pool_tmp, ignore_errors=True)
    code, what = _FORCED_EXITS[signal.Signals(signum)]
    line = f"ERROR: {what} {when}; working files removed, nothing was written to the input"
    with contextlib.suppress(OSError, ValueError):  # SIGHUP: the terminal may be gone
        sys.stderr.write(printable(line + "".join(f"; {n}" for n in notes)) + "\n")
        sys.stderr.flush()
    os._exit(code)


def _stop_children() -> None:
    """Kill this process's workers, which would otherwise hold its stderr and semaphores until reaped."""
    import multiprocessing

    for child in multiprocessing.active_children():
        with contextlib.suppress(Exception):
            child.kill()


def _release_semaphores() -> None:
    """Unlink the pool's semaphores as their finalizers would (else the tracker warns after ``os._exit``)."""
    import multiprocessing.synchronize
    import multiprocessing.util as mp_util

    cleanup = getattr(multiprocessing.synchronize.SemLock, "_cleanup", None)
    for finalizer in list(getattr(mp_util, "_finalizer_registry", {}).values()):
        if cleanup is not None and getattr(finalizer, "_callback", None) is cleanup:
            with contextlib.suppress(Exception):
                finalizer()


def install_signal_handlers() -> None:
    """SIGTERM raises :class:`~colmap_miho.errors.Terminated` to clean up like Ctrl-C; pycolmap
    (glog's handler) is imported first, then replaced. Signals ignored at start (``nohup``) stay
    ignored."""
    handlers = {**{sig: _raise_terminated for sig in _TERMINATING}, signal.SIGINT: _raise_interrupted}
    ignored = {sig for sig in handlers if signal.getsignal(sig) == signal.SIG_IGN}
    try:
        import pycolmap  # noqa: F401
    except ImportError:  # pragma: no cover - a broken install reports itself later
        pass
    for sig, handler in handlers.items():
        signal.signal(sig, signal.SIG_IGN if sig in ignored else handler)


def _glog_to_stderr():
    """COLMAP's log on stderr, never in glog's files in ``$TMPDIR``; a no-op without pycolmap."""
    try:
        from .sfm.colmap_log import glog_to_stderr

        return glog_to_stderr()
    except ImportError:  # pragma: no cover - a broken install reports itself later
        return contextlib.nullcontext()


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _notes(exc: BaseException) -> str:
    return "".join(f"; {' '.join(str(n).split())}" for n in getattr(exc, "__notes__", ()))


def _what_was_written(exc: BaseException) -> str:
    """What a signal's line says of the files: nothing written, or that the run was done."""
    if getattr(exc, "output_written", False):
        return "it came after the commit"
    return "working files removed, nothing was written to the input"


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; return the exit code: 0 ok, 1 failed run or internal error, 2 bad input
    (:class:`~colmap_miho.errors.UserError`), 130 Ctrl-C, 143 SIGTERM."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    verbose = getattr(args, "verbose", False)
    configure_logging(verbose, getattr(args, "quiet", False))
    in_main_thread = threading.current_thread() is threading.main_thread()
    saved = {sig: signal.getsignal(sig) for sig in (*_TERMINATING, signal.SIGINT)}
    if in_main_thread:
        _SIGNAL_HANDLED.clear()
        install_signal_handlers()
    guard = _forced_exit_after_sigterm() if in_main_thread else contextlib.nullcontext()
    glog = _glog_to_stderr()
    try:
        guard.__enter__()
        glog.__enter__()
        from .validation import check_options

        check_options(args)  # numeric options in range before any path is looked at
        from .adapters.staged_write import sweep_stale_tempdirs

        sweep_stale_tempdirs()  # what killed runs left in TMPDIR
        if args._paths is not None:
            from .adapters.paths import check_distinct

            check_distinct(*args._paths(args))
        code = int(args._run(args) or 0)
        if in_main_thread and _SIGNAL_HANDLED.is_set():  # raised inside a compiled callback, which swallowed it
            log.warning("a signal (Ctrl-C, SIGTERM or SIGHUP) arrived inside a compiled kernel, which lost it; "
                        "the run went on and finished: its output is complete")
        return code
    except UserError as exc:
        log.error("%s", _one_line(exc))
        return exc.exit_code
    except (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError) as exc:
        # a path the user gave that is missing, of the wrong kind or not allowed
        log.error("%s", _one_line(exc))
        return 2
    except Terminated as exc:
        code, what = _FORCED_EXITS.get(getattr(exc, "signum", signal.SIGTERM), _FORCED_EXITS[signal.SIGTERM])
        with contextlib.suppress(OSError, ValueError):  # SIGHUP: the terminal may be gone
            log.error("%s; %s%s", what, _what_was_written(exc), _notes(exc))
        return code
    except KeyboardInterrupt as exc:
        log.error("interrupted; %s%s", _what_was_written(exc), _notes(exc))
        return 130
    except (OSError, sqlite3.Error, MemoryError) as exc:
        # disk full, read-only folder, a truncated or corrupt file: one line, not a traceback
        log.error("%s%s%s", _one_line(exc), _notes(exc), "" if verbose else " (run with -v for details)",
                  exc_info=verbose)
        return 1
    except Exception as exc:  # noqa: BLE001 - no traceback reaches a user without -v
        log.error("%s: %s%s (unexpected; run with -v for the traceback and report it)",
                  type(exc).__name__, _one_line(exc), _notes(exc), exc_info=verbose)
        return 1
    finally:
        glog.__exit__(None, None, None)
        guard.__exit__(None, None, None)
        if in_main_thread:
            for sig, handler in saved.items():
                signal.signal(sig, handler)


def console_main() -> None:
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    console_main()
