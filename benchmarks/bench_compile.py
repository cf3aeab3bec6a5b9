"""Compile time of the compiled (numba) kernels per family, cold (an empty cache) and warm.

Every measurement runs in a fresh child process of this interpreter, its numba cache in a
folder of its own (``COLMAP_MIHO_CACHE_DIR`` and ``NUMBA_CACHE_DIR`` both point there): "cold"
starts from an empty folder (every kernel compiles), "warm" reuses the folder the cold run
filled (every kernel loads from the cache). A child imports numpy, torch and numba first
(``import`` column), then times one family's warm-up (the small synthetic call that reaches
every kernel of the family; ``load`` column):

- ``filter``: MOP+MiHo's kernels (``colmap_miho.filtering.preload``);
- ``ncc``: the NCC search and sub-pixel step (``refinement.ncc.kernel.warm``);
- ``lsm``: the least-squares matching step (``refinement.lsm.kernel.warm``);
- ``rectify``: the local affine fits (``refinement.rectify.kernel.warm``);
- ``all``: the four in one process, one after the other.

With ``--parallel N`` a last row compiles the four families cold in N processes at once (the
wall time until the last one ends). With ``--demo`` the built-in demo (``colmap-miho demo
--quick``) runs cold, then warm, then (where the ``compile`` command exists) cold again after
``colmap-miho compile``, and the table gives each run's wall time.

    python benchmarks/bench_compile.py [--repeats 3] [--families filter ncc lsm rectify all]
        [--parallel 2] [--demo] [--demo-args "--quick"]

Prints min and max over the repeats; on a machine shared with other work the spread is wide.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: the code that loads each family, valid on every version of the package.
FAMILY_CODE = {
    "filter": "from colmap_miho.filtering import preload; preload.warm()",
    "ncc": "from colmap_miho.refinement.ncc import kernel; kernel.warm()",
    "lsm": "from colmap_miho.refinement.lsm import kernel; kernel.warm()",
    "rectify": "from colmap_miho.refinement.rectify import kernel; kernel.warm()",
}
FAMILY_CODE["all"] = "; ".join(FAMILY_CODE[f] for f in ("filter", "ncc", "lsm", "rectify"))

_CHILD = """
import json, time
t0 = time.perf_counter()
import numpy, torch, numba
import colmap_miho.filtering.api, colmap_miho.refinement.warping
t1, c1 = time.perf_counter(), time.process_time()
{code}
t2, c2 = time.perf_counter(), time.process_time()
print(json.dumps({{"import": t1 - t0, "load": t2 - t1, "load_cpu": c2 - c1}}))
"""


def child_env(cache: Path) -> dict[str, str]:
    """This process's environment with the numba cache in ``cache`` (the worktree's code first)."""
    env = dict(os.environ, COLMAP_MIHO_CACHE_DIR=str(cache), NUMBA_CACHE_DIR=str(cache),
               PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]))
    return env


def time_family(family: str, cache: Path) -> dict[str, float]:
    """Import and load seconds of one family in a fresh child process with cache ``cache``."""
    out = subprocess.run([sys.executable, "-c", _CHILD.format(code=FAMILY_CODE[family])], env=child_env(cache),
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def time_parallel(n: int, cache: Path) -> float:
    """Wall seconds of the four families compiled cold in ``n`` child processes at once (the
    families handed out in order as processes end)."""
    todo = ["filter", "ncc", "lsm", "rectify"]
    running: list[subprocess.Popen] = []
    t0 = time.perf_counter()
    while todo or running:
        while todo and len(running) < n:
            fam = todo.pop(0)
            running.append(subprocess.Popen([sys.executable, "-c", _CHILD.format(code=FAMILY_CODE[fam])],
                                            env=child_env(cache), stdout=subprocess.DEVNULL))
        for p in list(running):
            if p.poll() is not None:
                if p.returncode:
                    raise RuntimeError(f"a compile process failed ({p.returncode})")
                running.remove(p)
        time.sleep(0.05)
    return time.perf_counter() - t0


def run_cli(args: list[str], cache: Path, cwd: Path) -> tuple[float, float]:
    """Wall and CPU seconds of ``colmap-miho ARGS`` (``python -m colmap_miho``) with cache
    ``cache``; the CPU of all its processes (the forkserver and workers included, which it never
    waits for: sampled, see ``bench_lsm_time.CpuMeter``)."""
    from bench_lsm_time import CpuMeter

    t0 = time.perf_counter()
    with CpuMeter() as cpu:
        subprocess.run([sys.executable, "-m", "colmap_miho", *args], env=child_env(cache), cwd=cwd, check=True,
                       stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0, cpu.seconds


def has_compile_command() -> bool:
    out = subprocess.run([sys.executable, "-m", "colmap_miho", "compile", "--help"], env=child_env(Path("/")),
                         capture_output=True)
    return out.returncode == 0


def spread(values: list[float]) -> str:
    return f"{min(values):6.1f} {max(values):6.1f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--families", nargs="*", default=["filter", "ncc", "lsm", "rectify", "all"],
                        choices=list(FAMILY_CODE))
    parser.add_argument("--parallel", type=int, default=0, help="also compile the four families in N processes")
    parser.add_argument("--demo", action="store_true", help="also time the demo cold, warm and after the compile step")
    parser.add_argument("--demo-args", default="--quick", help="arguments of the demo (default --quick)")
    args = parser.parse_args(argv)

    print(f"# {' '.join(['python', 'benchmarks/bench_compile.py', *(argv if argv is not None else sys.argv[1:])])}")
    print(f"# {os.cpu_count()} cores; seconds, min and max of {args.repeats} runs")
    print(f"{'family':10s} {'import min max':>14s} {'cold min max':>14s} {'cold CPU':>14s} {'warm min max':>14s}")
    with tempfile.TemporaryDirectory(prefix="bench_compile_") as tmp:
        for fam in args.families:
            imp, cold, cold_cpu, warm = [], [], [], []
            for r in range(args.repeats):
                cache = Path(tmp) / f"{fam}-{r}"
                c = time_family(fam, cache)
                w = time_family(fam, cache)
                imp.append(c["import"])
                cold.append(c["load"])
                cold_cpu.append(c["load_cpu"])
                warm.append(w["load"])
            print(f"{fam:10s} {spread(imp):>14s} {spread(cold):>14s} {spread(cold_cpu):>14s} {spread(warm):>14s}",
                  flush=True)
        if args.parallel:
            walls = [time_parallel(args.parallel, Path(tmp) / f"par-{r}") for r in range(args.repeats)]
            print(f"{f'all in {args.parallel} processes (wall)':30s} {spread(walls)}", flush=True)
        if args.demo:
            demo = ["demo", *shlex.split(args.demo_args), "-q"]
            rows: dict[str, list[tuple[float, float]]] = {"cold": [], "warm": []}
            compile_step = has_compile_command()
            if compile_step:
                rows.update({"compile step": [], "after compile": []})
            for r in range(args.repeats):
                cache, work = Path(tmp) / f"demo-{r}", Path(tmp) / f"work-{r}"
                work.mkdir()
                rows["cold"].append(run_cli([*demo, "--output", "a"], cache, work))
                rows["warm"].append(run_cli([*demo, "--output", "b"], cache, work))
                if compile_step:
                    cache2 = Path(tmp) / f"demo2-{r}"
                    rows["compile step"].append(run_cli(["compile", "-q"], cache2, work))
                    rows["after compile"].append(run_cli([*demo, "--output", "c"], cache2, work))
            print(f"demo {args.demo_args!r}: {'wall min max':>14s} {'CPU min max':>14s}")
            for name, values in rows.items():
                print(f"  {name:14s} {spread([v[0] for v in values]):>14s} {spread([v[1] for v in values]):>14s}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
