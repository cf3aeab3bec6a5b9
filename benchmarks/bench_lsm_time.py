"""Refine-stage time of NCC alone and NCC + LSM, alternated back to back on one database.

Runs ``refine_database`` on ``--database`` (e.g. a database cached by ``bench_accuracy.py``
under ``/tmp/bench_accuracy/<scene>/default/database.db``) with ``--ncc-recipe`` (default the
shipped ``mop_miho_ncc``) and ``--lsm-recipe`` (default ``mop_miho_lsm``: 17x17 LSM templates)
plus ``--set`` overrides, ``--repeats`` times each, alternating, and prints for every run the
refine stage's wall time and the CPU time of the whole run (this process and its worker
processes, the workers sampled every 0.2 s, so up to 0.2 s of each worker's end is missed).
The filter stage costs the same in both runs, so the CPU difference is the LSM step's. With
``--workers 1`` (everything in this process) ``--lsm-share`` also prints the CPU time of the
refine stage and of the LSM step inside it (``refine_pair``'s calls of ``lsm_step``). With
``--torch-lsm`` (``--workers 1``) a third run per repeat, ``lsm_torch``, takes the LSM recipe
with the LSM step on its torch path (``lsm_step(..., compiled=False)``, the reference of the
compiled kernel that CPU runs use). On a shared machine compare runs taken back to back only,
and prefer the CPU times.

    python benchmarks/bench_lsm_time.py --database DB --images DIR [--repeats 3] [--workers 2]
        [--ncc-recipe colmap_miho/recipes/mop_miho_ncc.toml] [--lsm-recipe colmap_miho/recipes/mop_miho_lsm.toml]
        [--set lsm.radius=6] [--lsm-share] [--torch-lsm]
"""

from __future__ import annotations

import argparse
import functools
import statistics
import threading
import time
from pathlib import Path

from colmap_miho.pipeline.refine_job import refine_database
from colmap_miho.recipe import load_recipe

REPO = Path(__file__).resolve().parents[1]


class CpuMeter:
    """CPU seconds (user + system) of this process and of every process it started, the
    others sampled every ``period`` seconds while the block runs (their last values count)."""

    def __init__(self, period: float = 0.2) -> None:
        self.period = period
        self.seconds = 0.0

    def __enter__(self) -> CpuMeter:
        import psutil

        self._error = psutil.Error
        self._me = psutil.Process()
        self._seen: dict[int, float] = {}
        self._before = self._own()
        self._before_kids = self._sample()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _own(self) -> float:
        t = self._me.cpu_times()
        return t.user + t.system

    def _sample(self) -> dict[int, float]:
        out = {}
        for p in self._me.children(recursive=True):
            try:
                t = p.cpu_times()
            except self._error:
                continue
            out[p.pid] = t.user + t.system
        return out

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self._seen.update(self._sample())

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._seen.update(self._sample())
        kids = sum(v - self._before_kids.get(pid, 0.0) for pid, v in self._seen.items())
        self.seconds = self._own() - self._before + kids


class StageClock:
    """Process CPU seconds spent in ``module.name`` while installed (one thread: this
    process's time is the function's)."""

    def __init__(self, module, name: str) -> None:
        self.module, self.name, self.seconds = module, name, 0.0
        self._orig = getattr(module, name)

        def timed(*args, **kwargs):
            t = time.process_time()
            try:
                return self._orig(*args, **kwargs)
            finally:
                self.seconds += time.process_time() - t

        setattr(module, name, timed)

    def remove(self) -> None:
        setattr(self.module, self.name, self._orig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--database", required=True)
    ap.add_argument("--images", required=True)
    ap.add_argument("--output-dir", default="/tmp")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ncc-recipe", default=str(REPO / "colmap_miho" / "recipes" / "mop_miho_ncc.toml"))
    ap.add_argument("--lsm-recipe", default=str(REPO / "colmap_miho" / "recipes" / "mop_miho_lsm.toml"))
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="LSM run overrides")
    ap.add_argument("--lsm-share", action="store_true",
                    help="with --workers 1: CPU time of the refine stage and of the LSM step in it")
    ap.add_argument("--torch-lsm", action="store_true",
                    help="with --workers 1: also time the LSM recipe with the LSM step's torch path")
    args = ap.parse_args(argv)
    if (args.lsm_share or args.torch_lsm) and args.workers != 1:
        ap.error("--lsm-share and --torch-lsm need --workers 1 (the stages run in this process)")
    recipes = {"ncc": load_recipe(args.ncc_recipe, []),
               "lsm": load_recipe(args.lsm_recipe, ["lsm.enabled=true", *args.overrides])}
    if args.torch_lsm:
        recipes["lsm_torch"] = recipes["lsm"]
    import colmap_miho.pipeline.refine_job as run_mod
    import colmap_miho.refinement.pairwise as ncc_mod

    step = ncc_mod.lsm_step
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in recipes}
    for _ in range(args.repeats):
        for name, rec in recipes.items():
            clocks = []
            if name == "lsm_torch":
                ncc_mod.lsm_step = functools.partial(step, compiled=False)
            if args.lsm_share:
                clocks = [StageClock(run_mod, "run_refine_keypoints"), StageClock(ncc_mod, "lsm_step")]
            try:
                with CpuMeter() as cpu:
                    s = refine_database(args.database, args.images, f"{args.output_dir}/bench_lsm_time_{name}.db",
                                        recipe=rec, overwrite=True, restart=True, workers=args.workers, seed=0)
            finally:
                for c in clocks:
                    c.remove()
                ncc_mod.lsm_step = step
            times[name].append((s.seconds["refine"], cpu.seconds))
            share = ""
            if clocks:
                share = (f"; refine stage {clocks[0].seconds:.1f} s CPU, LSM step {clocks[1].seconds:.1f} s CPU"
                         f" ({100 * clocks[1].seconds / max(clocks[0].seconds, 1e-9):.0f}%)")
            print(f"{name}: refine {s.seconds['refine']:.1f} s wall, run {cpu.seconds:.1f} s CPU{share}", flush=True)
    for name, ts in times.items():
        print(f"{name}: refine wall " + ", ".join(f"{w:.1f}" for w, _ in ts) + " s; run CPU "
              + ", ".join(f"{c:.1f}" for _, c in ts) + " s")
    med = {k: (statistics.median(w for w, _ in ts), statistics.median(c for _, c in ts)) for k, ts in times.items()}
    for name in [k for k in med if k != "ncc"]:
        print(f"median refine wall {name} / ncc = {med[name][0] / med['ncc'][0]:.2f}; median run CPU "
              f"{name} - ncc = {med[name][1] - med['ncc'][1]:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
