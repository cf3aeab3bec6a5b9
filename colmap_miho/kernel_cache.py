"""Filling the compiled kernels' cache ahead, once per cache folder, by kernel family.

The numba kernels (:mod:`.compiled`) compile on first use and are kept in the cache folder of
:func:`.compiled.cache_dir`; a process that finds them there loads them in well under a second
per family instead of compiling them (tens of seconds per family). The kernels come in four
families (:data:`FAMILIES`), each loaded by its own small synthetic call:

- ``filter``: MOP+MiHo's sampling, scoring, RANSAC and rotation kernels (every recipe);
- ``ncc``: the NCC search and sub-pixel step of the track walk (recipes that refine);
- ``lsm``: the least-squares matching step (``lsm.enabled`` or ``tracks.multiphoto_lsm``);
- ``rectify``: the local affine fits (``rectify.mode`` ``local`` or ``both``).

:func:`ensure_compiled` compiles the families a recipe uses (:func:`families_for`) that the
cache lacks, each in a child process of its own, several at once (numba compiles one function
at a time per process), and logs at INFO level what it compiles and how long it took;
``refine_database`` calls it before its workers start, ``colmap-miho compile`` calls it on its
own (a Dockerfile's build step, a cluster's setup), and on Dask each worker calls it once
(:mod:`.pipeline.dask_kernels`). A family is known to be in the cache by a ready file written
after its child succeeded, named by a key of the family's kernel sources (their paths and
contents), numba's and Python's versions and this machine's CPU, the things numba's own
cache entries depend on; a lock file keeps two processes from compiling into one folder at
once (the second waits, then finds the families ready).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import compiled
from .compiled import cache_dir, writable
from .enums import Rectification

log = logging.getLogger(__name__)

_PACKAGE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Family:
    """One kernel family: its loader (``module:function``, never raises) and its source paths or globs."""

    warm: str
    sources: tuple[str, ...]


#: the kernel families, in the order they are compiled (longest first).
FAMILIES: dict[str, Family] = {
    "filter": Family("colmap_miho.filtering.preload:warm", ("filtering/compiled/*.py", "filtering/preload.py")),
    "rectify": Family("colmap_miho.refinement.rectify.kernel:warm", ("refinement/rectify/kernel.py",)),
    "ncc": Family("colmap_miho.refinement.ncc.kernel:warm", ("refinement/ncc/kernel.py",)),
    "lsm": Family("colmap_miho.refinement.lsm.kernel:warm", ("refinement/lsm/kernel.py",)),
}

#: the ready files' folder inside the cache folder.
READY_FOLDER = "colmap-miho-ready"


def families_for(recipe) -> tuple[str, ...]:
    """The kernel families a :class:`~colmap_miho.recipe.Recipe` runs on the CPU, in
    :data:`FAMILIES` order: the filter's always; with ``pipeline.refine_keypoints`` the NCC kernels, the
    local affine fits with ``rectify.mode`` ``local`` or ``both``, the LSM step with
    ``lsm.enabled`` or ``tracks.multiphoto_lsm``."""
    used = {"filter"}
    if recipe.pipeline.refine_keypoints:
        used.add("ncc")
        if recipe.ncc.rectify.mode != Rectification.FILTER:
            used.add("rectify")
        if recipe.ncc.lsm.enabled or recipe.tracks.multiphoto_lsm:
            used.add("lsm")
    return tuple(f for f in FAMILIES if f in used)


@functools.lru_cache(maxsize=1)
def _machine() -> str:
    """What numba's cache keys hold beyond the source (its version, target CPU), read without numba."""
    from importlib.metadata import version

    import llvmlite.binding as llvm

    return "|".join((version("numba"), llvm.get_process_triple(),
                     os.environ.get("NUMBA_CPU_NAME") or llvm.get_host_cpu_name(),
                     os.environ.get("NUMBA_CPU_FEATURES") or llvm.get_host_cpu_features().flatten()))


def source_files(family: str) -> list[Path]:
    """The files ``family``'s compiled code comes from: its sources and :mod:`.compiled`."""
    return [path for name in (*FAMILIES[family].sources, "compiled.py") for path in sorted(_PACKAGE.glob(name))]


def ready_file(family: str, folder: Path | None = None) -> Path:
    """The file whose presence says ``family``'s current kernels are in ``folder``."""
    digest = hashlib.sha256()
    for path in source_files(family):
        digest.update(f"{path}\0".encode())
        digest.update(path.read_bytes())
    digest.update(f"{sys.version}\0{_machine()}".encode())
    return (folder or cache_dir()) / READY_FOLDER / f"{family}-{digest.hexdigest()[:20]}"


def cached(family: str, folder: Path | None = None) -> bool:
    """Whether ``family``'s kernels are in the cache folder (its :func:`ready_file` exists)."""
    return ready_file(family, folder).is_file()


@dataclass(frozen=True)
class CompileReport:
    """What :func:`ensure_compiled` did: the folder, whether writable, the families cached, compiled
    (seconds) and failed (why), and the wall time."""

    folder: Path
    writable: bool = True
    cached: tuple[str, ...] = ()
    compiled: dict[str, float] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0


@contextlib.contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    """An exclusive ``flock`` on the cache folder's lock file, waited for (and said so)."""
    ready = folder / READY_FOLDER
    ready.mkdir(parents=True, exist_ok=True)
    fd = os.open(ready / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("waiting for the kernels being compiled into %s", folder)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


_CHILD = ("import sys; sys.path.insert(0, {root!r}); "
          "from colmap_miho.kernel_cache import _compile_family; sys.exit(_compile_family({family!r}))")


def _compile_family(family: str) -> int:
    """In a child process: compile one family (0 when loaded); ends if its parent is gone."""
    import importlib

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()

    module, function = FAMILIES[family].warm.split(":")
    if getattr(importlib.import_module(module), function)():
        return 0
    print(f"the {family} kernels did not load: run any command that uses them with -v for the error",
          file=sys.stderr)
    return 1


def ensure_compiled(families: Iterable[str] = tuple(FAMILIES), *, processes: int | None = None) -> CompileReport:
    """Compile the ``families`` the cache lacks in child processes (up to ``processes`` at once) and
    mark them ready; logs at INFO. A failed compilation is reported, not raised; ValueError for an
    unknown name."""
    t0 = time.perf_counter()
    wanted = set(families)
    names = [f for f in FAMILIES if f in wanted]
    unknown = sorted(wanted - set(FAMILIES))
    if unknown:
        raise ValueError(f"unknown kernel families {unknown}; known: {list(FAMILIES)}")
    folder = cache_dir()
    if not writable(folder):
        return CompileReport(folder=folder, writable=False, seconds=time.perf_counter() - t0)
    with _folder_lock(folder):
        missing = [f for f in names if not cached(f, folder)]
        have = tuple(f for f in names if f not in missing)
        if not missing:
            return CompileReport(folder=folder, cached=have, seconds=time.perf_counter() - t0)
        n = max(1, min(len(missing), processes or os.cpu_count() or 1))
        log.info("compiling kernels (first run, once per cache): %s, %d at a time, into %s",
                 ", ".join(missing), n, folder)
        done, failed = _compile_children(missing, n, folder)
        for family in done:
            path = ready_file(family, folder)
            path.write_text(f"{family} compiled in {done[family]:.1f} s\n")
    seconds = time.perf_counter() - t0
    if done:
        log.info("compiled the kernels in %.1f s (%s)", seconds,
                 ", ".join(f"{f} {s:.1f} s" for f, s in done.items()))
    return CompileReport(folder=folder, cached=have, compiled=done, failed=failed, seconds=seconds)


def _compile_children(families: list[str], n: int, folder: Path) -> tuple[dict[str, float], dict[str, str]]:
    """One child per family, ``n`` at once; returns (seconds of successes, why of failures)."""
    env = dict(os.environ, **{compiled.CACHE_ENV: str(folder)})
    todo = list(families)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    errors: dict[str, Any] = {}  # family -> its child's stderr (a file: a pipe could fill up)
    done: dict[str, float] = {}
    failed: dict[str, str] = {}
    try:
        while todo or running:
            while todo and len(running) < n:
                family = todo.pop(0)
                code = _CHILD.format(root=str(_PACKAGE.parent), family=family)
                errors[family] = tempfile.TemporaryFile("w+")
                running[family] = (subprocess.Popen([sys.executable, "-c", code], env=env, stdin=subprocess.DEVNULL,
                                                    stdout=subprocess.DEVNULL, stderr=errors[family]),
                                   time.perf_counter())
            family = _wait_any(running)
            proc, start = running.pop(family)
            errors[family].seek(0)
            err = errors[family].read()
            if proc.returncode == 0:
                done[family] = time.perf_counter() - start
                log.info("compiled the %s kernels in %.1f s", family, done[family])
            else:
                lines = err.strip().splitlines()
                failed[family] = lines[-1] if lines else f"exit status {proc.returncode}"
                log.warning("could not compile the %s kernels ahead (%s): they compile where they are used",
                            family, failed[family])
    finally:
        for proc, _ in running.values():  # interrupted: the children go with this process
            proc.kill()
            proc.wait()
        for file in errors.values():
            file.close()
    return done, failed


def _wait_any(running: dict[str, tuple[subprocess.Popen, float]]) -> str:
    """The first family whose child process ended (polled every 50 ms)."""
    while True:
        for family, (proc, _) in running.items():
            if proc.poll() is not None:
                return family
        time.sleep(0.05)


def load_cached() -> tuple[str, ...]:
    """Load every cached family here (all of them where the folder is read-only); never raises."""
    folder = cache_dir()
    usable = writable(folder)
    loaded = []
    for family, spec in FAMILIES.items():
        try:
            if usable and not cached(family, folder):
                continue
            import importlib

            module, function = spec.warm.split(":")
            if getattr(importlib.import_module(module), function)():
                loaded.append(family)
        except Exception:  # noqa: BLE001 - loading ahead is optional; the real call reports the error
            continue
    return tuple(loaded)


_BACKGROUND: list[threading.Thread] = []  # the running compile_in_background thread, if any


def compile_in_background(families: Iterable[str]) -> threading.Thread:
    """:func:`ensure_compiled` in a daemon thread, so a job compiles while it extracts or maps; the
    refine step's own call then waits on the lock and finds them ready."""
    names = tuple(families)

    def work() -> None:
        try:
            ensure_compiled(names)
        except Exception as exc:  # noqa: BLE001 - the refine step compiles (and reports) itself
            log.debug("compiling the kernels in the background failed: %s", exc)

    if _BACKGROUND and _BACKGROUND[0].is_alive():
        return _BACKGROUND[0]
    thread = threading.Thread(target=work, name="kernel-compile", daemon=True)
    thread.start()
    _BACKGROUND[:] = [thread]
    return thread
