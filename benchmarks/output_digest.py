"""Digests of what ``refine`` writes, to show that a change leaves every output bit-identical.

For the demo scene and the shared multi-view scenes, in both COLMAP matching settings, the input
database is built once (as ``bench_accuracy.py`` builds it, cached under ``--work``), then
``refine_database`` runs with each recipe (and ``--set`` overrides); every output's written
tables (keypoints, matches, two-view geometries, row by row and blob by blob) are hashed. Run it
before and after a change (same ``--workers``: the global mapper of the match check is
multi-threaded) and compare the two JSON files with ``--compare``::

    python benchmarks/output_digest.py --json before.json [--recipes mop_miho_lsm mop_miho_ncc]
        [--set match_check.mode=remove] [--scenes demo strecha_castle_p19 ...]
    python benchmarks/output_digest.py --compare before.json after.json

``--databases A.db B.db ...`` only hashes those outputs (e.g. one refine run on the process pool
and one on ``--dask``) and says whether they are identical.

``--demo-all-recipes`` adds every built-in recipe on the demo scene.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import DEMO, SETTINGS, SHARED_SCENES, scene_databases  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
#: Tables ``refine`` writes, and the column that orders their rows.
WRITTEN_TABLES = {"keypoints": "image_id", "matches": "pair_id", "two_view_geometries": "pair_id"}


def digest(path: Path) -> dict[str, str]:
    """sha256 of each written table of the database at ``path`` (rows ordered by their key)."""
    import sqlite3

    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        out = {}
        for table, key in WRITTEN_TABLES.items():
            h = hashlib.sha256()
            for row in con.execute(f"SELECT * FROM {table} ORDER BY {key}"):  # noqa: S608 - fixed names
                h.update(repr(row).encode())
            out[table] = h.hexdigest()[:16]
        return out
    finally:
        con.close()


def compare(a: Path, b: Path) -> int:
    """Print the runs of ``a`` and ``b`` whose digests differ; 1 when any does (or one is missing)."""
    ra = {r["run"]: r for r in json.loads(a.read_text())["rows"]}
    rb = {r["run"]: r for r in json.loads(b.read_text())["rows"]}
    bad = 0
    for run in sorted(set(ra) | set(rb)):
        if run not in ra or run not in rb:
            print(f"{run}: only in {'before' if run in ra else 'after'}")
            bad += 1
        elif ra[run]["digest"] != rb[run]["digest"]:
            print(f"{run}: DIFFERS {ra[run]['digest']} vs {rb[run]['digest']}")
            bad += 1
        else:
            print(f"{run}: identical")
    print(f"{len(set(ra) | set(rb)) - bad} identical, {bad} differ")
    return 1 if bad else 0


def compare_databases(paths: list[Path]) -> int:
    """Print the written tables' digests of each database; 0 when all are identical, else 1."""
    digests = []
    for p in paths:
        if not p.is_file():
            raise SystemExit(f"error: no database at {p}")
        digests.append(digest(p))
        print(f"{p}: {' '.join(f'{k}={v}' for k, v in digests[-1].items())}")
    same = all(d == digests[0] for d in digests)
    print("identical" if same else "DIFFER")
    return 0 if same else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_accuracy"), help="cache of scenes and databases")
    ap.add_argument("--out", type=Path, default=Path("/tmp/output_digest"), help="folder of the outputs")
    ap.add_argument("--scenes", nargs="+", default=[DEMO, *SHARED_SCENES])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--recipes", nargs="+", default=["mop_miho_lsm"])
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--demo-all-recipes", action="store_true", help="every built-in recipe on the demo too")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    ap.add_argument("--databases", nargs="+", type=Path, metavar="DB",
                    help="only the digests of these refine outputs, and whether they are identical")
    args = ap.parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    if args.databases:
        return compare_databases(args.databases)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    import pycolmap

    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.recipe import available_recipes, load_recipe

    pycolmap.logging.minloglevel = 1
    rows = []
    for scene, setting, image_dir, db in scene_databases(args.scenes, args.settings, args.data, args.work,
                                                         args.max_features):
        recipes = list(args.recipes)
        if scene == DEMO and args.demo_all_recipes:
            recipes += [r for r in available_recipes() if r not in recipes]
        for name in recipes:
            run = f"{scene}/{setting}/{name}"
            out = args.out / scene / setting / f"{name}.db"
            out.parent.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            summary = refine_database(db, image_dir, out, recipe=load_recipe(name, args.overrides),
                                      overwrite=True, restart=True, workers=args.workers, seed=0)
            d = digest(summary.output)
            rows.append({"run": run, "digest": d, "seconds": round(time.perf_counter() - t0, 1)})
            print(f"{run}: {' '.join(d.values())} ({time.perf_counter() - t0:.1f} s)", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"argv": sys.argv[1:] if argv is None else list(argv),
                                         "overrides": args.overrides, "rows": rows}, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
