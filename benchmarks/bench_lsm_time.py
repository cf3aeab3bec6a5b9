"""Refine-stage time of NCC alone and NCC + LSM, alternated back to back on one database.

Runs ``refine_database`` on ``--database`` (e.g. a database cached by ``bench_accuracy.py``
under ``/tmp/bench_accuracy/<scene>/default/database.db``) with the default recipe and with the
same recipe plus ``ncc.lsm=true`` and ``--set`` overrides, ``--repeats`` times each, alternating,
and prints the refine stage's wall time of every run. On a shared machine compare runs taken
back to back only.

    python benchmarks/bench_lsm_time.py --database DB --images DIR [--repeats 3] [--workers 2]
        [--set ncc.lsm_radius=8]
"""

from __future__ import annotations

import argparse

from colmap_miho.pipeline.run import refine_database
from colmap_miho.recipe import load_recipe


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--database", required=True)
    ap.add_argument("--images", required=True)
    ap.add_argument("--output-dir", default="/tmp")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="LSM run overrides")
    args = ap.parse_args(argv)
    recipes = {"ncc": load_recipe("mop_miho_ncc", []),
               "lsm": load_recipe("mop_miho_ncc", ["ncc.lsm=true", *args.overrides])}
    times: dict[str, list[float]] = {k: [] for k in recipes}
    for _ in range(args.repeats):
        for name, rec in recipes.items():
            s = refine_database(args.database, args.images, f"{args.output_dir}/bench_lsm_time_{name}.db",
                                recipe=rec, overwrite=True, restart=True, workers=args.workers, seed=0)
            times[name].append(s.seconds["refine"])
            print(f"{name}: refine {times[name][-1]:.1f} s", flush=True)
    for name, ts in times.items():
        print(f"{name}: " + ", ".join(f"{t:.1f}" for t in ts) + " s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
