"""Worker processes: a pool forked from a forkserver that imported torch and the kernels once, one
BLAS/torch thread each (the walk's small tensor operations gain nothing from more), dying with their
parent; and per-pair seeds independent of the worker count."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from ..errors import RunFailed, UserError

log = logging.getLogger(__name__)

#: Seconds between two checks of the parent's pid by a worker's watchdog.
PARENT_POLL_S = 0.5

#: Modules the forkserver imports once for all the workers it forks.
PRELOAD = ("numpy", "torch", "colmap_miho.pipeline.filter", "colmap_miho.pipeline.refine_keypoints",
           "colmap_miho.refinement.pairwise", "colmap_miho.refinement.tracks.walk",
           "colmap_miho.kernel_preload")

#: What a script that starts workers needs (said by the errors of failed worker starts).
SCRIPT_HINT = ("if you call colmap_miho from your own script, put the call under 'if __name__ == "
               "\"__main__\":' (worker processes import the script that started them), or use "
               "one worker (--workers 1)")

#: The message of a run whose worker process ended abruptly.
WORKER_DIED = f"a worker process ended abruptly (killed, out of memory, or a crash in native code); {SCRIPT_HINT}"

_SINGLE_THREAD_ENV = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def init_worker() -> None:
    """One torch thread per worker process (the parallelism is across pairs)."""
    if "torch" in sys.modules:  # the filter is numpy; only pay for torch if it is loaded
        sys.modules["torch"].set_num_threads(1)


def _pid_alive(pid: int) -> bool:
    """Whether ``pid`` is a live process of ours; a zombie is not (a SIGKILLed parent stays one
    until reaped, and workers waiting on it would wait for ever)."""
    try:
        os.kill(pid, 0)
    except OSError:
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            state = fh.read().rpartition(b")")[2].split()[:1]
    except OSError:  # no /proc (macOS): the signal test alone
        return True
    return state not in ([b"Z"], [b"X"])


def _watch_parent(parent_pid: int, ppid: int) -> None:
    while True:
        # re-parented (the parent, or the forkserver between them, died), or the parent gone
        if os.getppid() != ppid or not _pid_alive(parent_pid):
            os._exit(1)
        time.sleep(PARENT_POLL_S)


def start_parent_watchdog(parent_pid: int) -> None:
    """In a worker: a daemon thread that ends this process once ``parent_pid`` is gone or it was re-parented."""
    ppid = os.getppid()
    if ppid != parent_pid and not _pid_alive(parent_pid):
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid, ppid), name="parent-watchdog",
                     daemon=True).start()


def _worker_start(parent_pid: int, initializer, initargs: tuple) -> None:
    start_parent_watchdog(parent_pid)
    if initializer is not None:
        initializer(*initargs)


@contextlib.contextmanager
def single_thread_children():
    """Spawned workers inherit the environment: make their BLAS/OpenMP single-threaded."""
    saved = {k: os.environ.get(k) for k in _SINGLE_THREAD_ENV}
    os.environ.update(_SINGLE_THREAD_ENV)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def sigint_for_this_process_only():
    """Processes started inside the block never receive SIGINT or SIGHUP (a terminal's Ctrl-C
    reaches the whole foreground group; workers would print tracebacks or die). This process gets a
    SIGINT that arrived meanwhile when the block ends. A no-op outside the main thread."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    from multiprocessing import resource_tracker

    hangup = {signal.SIGHUP} if hasattr(signal, "SIGHUP") else set()
    # first: starting it unblocks SIGINT after blocking it around its own start (bpo-33613);
    # it ignores SIGINT and SIGTERM itself, and inherits SIGHUP blocked (the terminal closing
    # sends SIGHUP to the whole group: a tracker killed by it is started again, and its
    # successor prints a KeyError traceback for every semaphore it never saw)
    old = signal.pthread_sigmask(signal.SIG_BLOCK, hangup)
    try:
        resource_tracker.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, *hangup})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


_FORKSERVER_FAILED: list[str] = []  # why the forkserver could not start (then: spawn)


def _context():
    """The forkserver context where there is one and it starts, else spawn."""
    if "forkserver" in multiprocessing.get_all_start_methods() and not _FORKSERVER_FAILED:
        return multiprocessing.get_context("forkserver")
    return multiprocessing.get_context("spawn")


#: Prefix of multiprocessing's temporary folder (see :func:`private_multiprocessing_tempdir`).
MP_TEMPDIR_PREFIX = "miho-mp-"
_MP_TEMPDIR: list = []  # the private_tempdir context of this process's folder, open until exit
#: Longest AF_UNIX socket path (bytes, without the final NUL) on Linux; the forkserver's socket
#: is ``<folder>/listener-XXXXXXXX``.
MAX_SOCKET_PATH = 107


def private_multiprocessing_tempdir() -> None:
    """Give multiprocessing a :func:`~colmap_miho.adapters.staged_write.private_tempdir` instead of
    its ``pymp-*`` folder, so a ``kill -9`` leaves nothing behind."""
    import multiprocessing.process
    import multiprocessing.util

    from ..adapters.staged_write import private_tempdir

    config = multiprocessing.process.current_process()._config  # type: ignore[attr-defined]
    if config.get("tempdir") is not None:
        return
    folder = private_tempdir(MP_TEMPDIR_PREFIX)
    try:
        path = folder.__enter__()
    except (OSError, UserError):  # a full TMPDIR: multiprocessing tries (and says) itself
        return
    if len(os.fsencode(path)) + len("/listener-12345678") > MAX_SOCKET_PATH:
        # the forkserver's socket would not fit where pymp-* (3 characters shorter) might
        folder.__exit__(None, None, None)
        return
    _MP_TEMPDIR.append(folder)
    config["tempdir"] = str(path)
    # removed last at exit, as multiprocessing removes its own pymp-* folder
    multiprocessing.util.Finalize(None, _close_mp_tempdir, exitpriority=-100)


def _close_mp_tempdir() -> None:
    import multiprocessing.process

    multiprocessing.process.current_process()._config.pop("tempdir", None)  # type: ignore[attr-defined]
    while _MP_TEMPDIR:
        with contextlib.suppress(Exception):
            _MP_TEMPDIR.pop().__exit__(None, None, None)


def start_forkserver() -> None:
    """Start the forkserver now with :data:`PRELOAD` imported, so its imports overlap this process's
    work; pools use spawn if it cannot start."""
    ctx = _context()
    if ctx.get_start_method() != "forkserver":
        return
    from multiprocessing import forkserver

    try:
        private_multiprocessing_tempdir()
        with single_thread_children(), sigint_for_this_process_only():
            ctx.set_forkserver_preload(list(PRELOAD))
            forkserver.ensure_running()
    except OSError as exc:
        _FORKSERVER_FAILED.append(str(exc))
        log.warning("worker processes are spawned (the forkserver did not start: %s)", exc)


@contextlib.contextmanager
def process_pool(workers: int, *, initializer=None, initargs: tuple = (), **kwargs):
    """A process pool whose workers die with this process and are killed, queue cancelled, when the block raises."""
    start_forkserver()
    with ProcessPoolExecutor(max_workers=workers, mp_context=_context(),
                             initializer=_worker_start, initargs=(os.getpid(), initializer, tuple(initargs)),
                             **kwargs) as ex:
        try:
            yield ex
        except BaseException as exc:
            procs = list((getattr(ex, "_processes", None) or {}).values())  # shutdown forgets them
            ex.shutdown(wait=False, cancel_futures=True)
            _kill(procs)
            if isinstance(exc, BrokenProcessPool):
                raise RunFailed(WORKER_DIED) from exc
            raise


def check_not_bootstrapping() -> None:
    """Refuse a run inside a worker still importing its parent's main script (no ``__main__`` guard); RunFailed."""
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise RunFailed("colmap_miho was called while a worker process imported the main script: "
                        "put the call under 'if __name__ == \"__main__\":'")



def _kill(procs: list) -> None:
    """SIGKILL worker processes (pure compute on copies: nothing to clean up) and reap them."""
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.kill()
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.join(timeout=5)
