"""Where the pipeline's parallel work runs: this process, a local process pool or a Dask cluster,
behind one :class:`Runner`; tasks have one BLAS/torch thread and only this process writes SQLite."""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future

from ..enums import RunnerKind
from ..errors import RunFailed, UserError
from .workers import SCRIPT_HINT, init_worker, process_pool, sigint_for_this_process_only, single_thread_children

log = logging.getLogger(__name__)

#: Seconds to wait for a Dask scheduler given by address before giving up.
CONNECT_TIMEOUT_S = 20

#: ``--dask`` value that starts a local cluster (``refine --dask`` without an address).
LOCAL = "local"


def _ready() -> bool:
    return True


def _one_thread_task(fn: Callable, *args):
    init_worker()
    return fn(*args)


class Runner:
    """The engine of one run: ``slots`` tasks at once, ``kind``
    (:class:`~colmap_miho.enums.RunnerKind`), Dask ``address`` ("" otherwise)."""

    def __init__(self, slots: int, kind: RunnerKind | str, address: str = "",
                 make_executor: Callable[[], Executor] | None = None,
                 wrap: bool = False) -> None:
        self.slots = max(1, int(slots))
        self.kind = RunnerKind.parse(kind, "kind")
        self.address = address
        self._make = make_executor
        self._executor: Executor | None = None
        self._wrap = wrap

    @property
    def started(self) -> bool:
        """Whether the executor runs already (a process pool that an earlier stage started)."""
        return self._executor is not None

    @property
    def parallel(self) -> bool:
        """Whether tasks go to other processes (False: call them in this process)."""
        return self._make is not None

    def executor(self) -> Executor:
        """The executor, started on first use (a pool costs seconds: workers import torch)."""
        if self._make is None:
            raise RuntimeError("an inline runner has no executor; call the function directly")
        if self._executor is None:
            self._executor = self._make()
        return self._executor

    def start_in_background(self) -> Callable[[], bool]:
        """Start the workers from a background thread; returns ``starting()``, True until a
        worker ran a first task. Submit only once it is False (it raises the start's error)."""
        if self._make is None or self._executor is not None:
            return lambda: False
        ex = self.executor()  # here: the pool's cleanup belongs to this thread
        failed: list[BaseException] = []

        def start() -> None:
            try:
                ex.submit(_ready).result()
            except BaseException as exc:
                failed.append(exc)

        thread = threading.Thread(target=start, name="pool-start", daemon=True)
        thread.start()

        def starting() -> bool:
            if thread.is_alive():
                return True
            if failed:
                raise failed[0]
            return False

        return starting

    def submit(self, fn: Callable, *args) -> Future:
        """Submit ``fn(*args)``; inline runners call it now and return a finished future."""
        if self._make is None:
            fut: Future = Future()
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:  # surfaced by fut.result(), as an executor would
                fut.set_exception(exc)
            return fut
        # a Ctrl-C inside submit (which may fork a worker) waits until it returns: a worker forked
        # but not yet known to the pool would outlive the run and print its own traceback
        with sigint_for_this_process_only():
            if self._wrap:
                return self.executor().submit(_one_thread_task, fn, *args)
            return self.executor().submit(fn, *args)


@contextlib.contextmanager
def open_runner(workers: int, dask: str | None = None, *, families: tuple[str, ...] = ()) -> Iterator[Runner]:
    """The engine for ``workers`` processes, or a Dask cluster (``dask``: :data:`LOCAL` or a
    scheduler address) whose workers load ``families`` first. UserError when Dask cannot be used."""
    if dask is None:
        if workers <= 1:
            yield Runner(1, RunnerKind.INLINE)
            return
        with contextlib.ExitStack() as stack:
            def start() -> Executor:
                stack.enter_context(single_thread_children())
                return stack.enter_context(process_pool(workers, initializer=init_worker))

            yield Runner(workers, RunnerKind.PROCESSES, make_executor=start)
        return
    with _dask_client(workers, dask) as client:
        if families:
            from .dask_kernels import load_kernels_on_workers

            load_kernels_on_workers(client, families)
        slots = sum(int(w.get("nthreads", 1)) for w in client.scheduler_info()["workers"].values())
        ex = client.get_executor(pure=False)
        runner = Runner(max(1, slots), RunnerKind.DASK, address=str(client.scheduler.address),
                        make_executor=lambda: ex, wrap=True)
        try:
            yield runner
        except BaseException:
            with contextlib.suppress(Exception):
                ex.shutdown(wait=False)
            raise


@contextlib.contextmanager
def _quiet_dask():
    """Silence Dask's "Sending large graph" warning and its shutdown tracebacks on Ctrl-C / SIGTERM."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
        try:
            yield
        except KeyboardInterrupt:
            for name in ("distributed", "tornado", "asyncio"):
                logging.getLogger(name).setLevel(logging.CRITICAL + 1)
            raise


@contextlib.contextmanager
def _dask_client(workers: int, dask: str):
    from ..extras import require

    distributed = require("distributed", "dask", "--dask")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if dask == LOCAL:
        from ..adapters.staged_write import private_tempdir
        from .workers import private_multiprocessing_tempdir

        private_multiprocessing_tempdir()
        # the workers' dask-scratch-space in a folder of ours: removed after the run (Dask
        # leaves it in TMPDIR), and by the next run after a kill -9
        import dask.config as dask_config  # (``dask`` is the argument)

        with private_tempdir("colmap_miho_dask_", own_failures=False) as scratch, \
                dask_config.set({"temporary-directory": str(scratch)}):
            try:
                with sigint_for_this_process_only():  # Ctrl-C: one line from this process, none from the workers
                    cluster = LocalCluster(n_workers=max(1, int(workers)), threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=logging.CRITICAL,
                                           local_directory=str(scratch))
            except RuntimeError as exc:  # "Nanny failed to start."
                raise RunFailed(f"the local Dask cluster did not start ({exc}); {SCRIPT_HINT}") from exc
            with cluster, Client(cluster) as client, _quiet_dask():
                log.info("started a local Dask cluster of %d workers at %s", workers, cluster.scheduler_address)
                yield client
        return
    if not dask.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
        raise UserError(f"--dask {dask}: give a scheduler address like tcp://host:8786, or no value "
                        "for a local cluster")
    from .scheduler_probe import check_dask_scheduler

    check_dask_scheduler(dask, connect_timeout=CONNECT_TIMEOUT_S)  # Client would wait forever on a mute service
    try:
        client = Client(dask, timeout=f"{CONNECT_TIMEOUT_S}s")
    except (OSError, TimeoutError) as exc:
        raise UserError(f"--dask {dask}: cannot reach the Dask scheduler ({exc})") from None
    with client, _quiet_dask():
        if not client.scheduler_info()["workers"]:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        yield client
