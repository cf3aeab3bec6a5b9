"""What a user gains end to end: COLMAP mapping alone against ``refine`` then mapping.

For each scene (the built-in demo scene and the multi-view scenes of the shared data) and each
COLMAP matching setting (``default``; ``permissive``: SIFT ratio 0.95, no cross-check), one run:

1. the input database, built and cached as ``bench_accuracy.py`` builds it (``--cache``; the
   build time is not part of the table);
2. COLMAP's incremental mapping of the input, timed;
3. ``refine_database`` of the input with the recipe (default: the project's default recipe;
   ``--recipe``, ``--set``) into a fresh output (overwrite, restart), timed, then the incremental
   mapping of its output, timed the same way;
4. with ``--oracle`` (default on): the GT-oracle database (every match farther than
   ``--oracle-threshold`` px, 4, from its GT epipolar line removed; :mod:`miho_bench.oracle`)
   mapped the same way, for its AUC only.

Every mapping is ``bench_known_cameras.py``'s (:func:`bench_known_cameras.map_runs`): the GT
intrinsics written into the mapped copy, ``mapping.refine_intrinsics=none``, mapper seed 0,
``--threads`` mapper threads (2), model pose AUC over all GT pairs. The mapping seconds are the
mapper call's wall time (``MappingResult.seconds``: the database copy and the AUC report are not
in it); the refine seconds are the wall time of the ``refine_database`` call. The ratio is
(refine + mapping of the refined database) / (mapping of the input): above 1, refining costs the
user time end to end; the AUC columns say what it buys.

    python benchmarks/bench_end_to_end.py [--data ../shared/data] [--cache /tmp/bench_accuracy]
        [--work /tmp/bench_end_to_end] [--scenes demo strecha_castle_p19 ...]
        [--settings default permissive] [--recipe NAME|PATH] [--set key=value] ...
        [--workers 2] [--threads 2] [--oracle | --no-oracle] [--oracle-threshold 4]
        [--max-features 4096] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from bench_accuracy import DEMO, MAX_FEATURES, SETTINGS, SHARED_SCENES, build_database, scene_inputs
from bench_known_cameras import map_runs, oracle_database, portable_argv

REPO = Path(__file__).resolve().parents[1]
AUC_DEG = 0.5  # the table's pose AUC threshold (degrees)
MATCH_CHECK = "match_check"  # the refine summary's stage name (summary.seconds key)


# --------------------------------------------------------------------------- rows
def mapping_figures(runs: list[dict]) -> dict:
    """The one run of :func:`bench_known_cameras.map_runs` as table figures: mapper seconds,
    AUC at ``AUC_DEG`` (a fraction; 0 for a failed mapping), registered and database images."""
    from colmap_miho.reporting.report import auc_key

    run = runs[0]
    return {"seconds": float(run["seconds"]), "auc": float(run[auc_key(AUC_DEG)]),
            "registered": int(run["num_reg_images"]), "images": int(run["num_images"])}


def mapped(database: Path, name: str, image_dir: Path, gt: Path, work: Path, mapping, intrinsics: dict,
           label: str) -> dict:
    """Map ``database`` once (seed 0) into ``work/name`` as ``bench_known_cameras.py`` does;
    :func:`mapping_figures` of the run (progress on stderr)."""
    figures = mapping_figures(map_runs(database, image_dir, gt, work / name, 1, mapping, intrinsics))
    print(f"{label}: mapping {name} {figures['seconds']:.1f} s, {figures['registered']}/{figures['images']} "
          f"registered, AUC@{AUC_DEG:g} {100 * figures['auc']:.1f} %", file=sys.stderr)
    return figures


def end_to_end_row(scene: str, setting: str, mapped_input: dict, refine_s: float, match_check_s: float | None,
                   mapped_refined: dict, oracle_auc: float | None) -> dict:
    """One table row from the measured figures (``mapped_*``: :func:`mapping_figures`); adds the
    total ``refine + mapping`` seconds and its ratio to the mapping of the input (None when that
    took no time)."""
    total = refine_s + mapped_refined["seconds"]
    alone = mapped_input["seconds"]
    return {"scene": scene, "setting": setting,
            "mapping_alone_s": alone, "refine_s": refine_s, "match_check_s": match_check_s,
            "refine_mapping_s": total, "ratio": total / alone if alone > 0 else None,
            "auc_input": mapped_input["auc"], "auc_refined": mapped_refined["auc"], "auc_oracle": oracle_auc,
            "registered_input": mapped_input["registered"], "registered_refined": mapped_refined["registered"],
            "images": mapped_input["images"], "mapping_refined_s": mapped_refined["seconds"]}


# --------------------------------------------------------------------------- table
HEAD = ["scene", "matching", "mapping alone (s)", "refine (s)", "match check (s)", "refine + mapping (s)",
        "ratio (refine+mapping)/(mapping alone)", f"AUC@{AUC_DEG:g} input (%)", f"AUC@{AUC_DEG:g} refined (%)",
        f"AUC@{AUC_DEG:g} oracle (%)", "registered input/refined"]


def _num(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table(rows: list[dict]) -> str:
    """Markdown table of :func:`end_to_end_row` rows, one line per scene / setting."""
    lines = ["| " + " | ".join(HEAD) + " |", "|---|---|" + "---:|" * (len(HEAD) - 2)]
    for r in rows:
        pct = [None if v is None else 100.0 * v for v in (r["auc_input"], r["auc_refined"], r["auc_oracle"])]
        cells = [r["scene"], r["setting"], _num(r["mapping_alone_s"], ".1f"), _num(r["refine_s"], ".1f"),
                 _num(r["match_check_s"], ".1f"), _num(r["refine_mapping_s"], ".1f"), _num(r["ratio"], ".2f"),
                 *[_num(v, ".1f") for v in pct],
                 f"{r['registered_input']}/{r['registered_refined']} of {r['images']}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (see the module docstring); a bad value exits with argparse's message."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_accuracy"),
                    help="database cache (shared with bench_accuracy.py; a missing database is built there)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_end_to_end"),
                    help="refined and oracle databases, models")
    ap.add_argument("--scenes", nargs="+", default=[DEMO, *SHARED_SCENES])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--recipe", default=None, help="refine recipe (default: the project's default)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="recipe override (repeatable)")
    ap.add_argument("--workers", type=int, default=2, help="refine_database workers (default 2)")
    ap.add_argument("--threads", type=int, default=2, help="mapper threads of every mapping (default 2)")
    ap.add_argument("--oracle", action=argparse.BooleanOptionalAction, default=True,
                    help="also map the GT-oracle database (AUC only; default on)")
    ap.add_argument("--oracle-threshold", type=float, default=4.0,
                    help="GT epipolar distance (px) above which the oracle removes a match")
    ap.add_argument("--max-features", type=int, default=4096, help="SIFT features per image (demo: 2048)")
    ap.add_argument("--json", type=Path, default=None, help="write the rows as JSON (after every row)")
    args = ap.parse_args(argv)
    if args.workers < 1 or args.threads < 1:
        ap.error("--workers and --threads must be >= 1")
    if not args.oracle_threshold > 0:
        ap.error("--oracle-threshold must be > 0")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from dataclasses import replace

    from colmap_miho.enums import Mapper
    from colmap_miho.recipe import load_recipe

    common = [f"mapping.num_threads={args.threads}", "mapping.refine_intrinsics=none"]
    try:  # a bad recipe or key fails here, before any work
        recipe = load_recipe(args.recipe, [*args.overrides, *common])
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    mapping = replace(recipe.mapping, mapper=Mapper.INCREMENTAL)

    import pycolmap

    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.reporting.compare import gt_intrinsics
    from colmap_miho.reporting.gt_model import load_gt_poses

    pycolmap.logging.minloglevel = 1
    cmd = portable_argv(sys.argv[1:] if argv is None else list(argv))
    t_all = time.perf_counter()
    rows: list[dict] = []
    for scene in args.scenes:
        found = scene_inputs(scene, args.data, args.cache)  # the demo is rendered into the cache
        if found is None:
            print(f"skip {scene}: no images/ or gt_model/ under {args.data / scene}", file=sys.stderr)
            continue
        image_dir, gt = found
        gt_poses, intrinsics = load_gt_poses(gt), gt_intrinsics(gt)
        for setting in args.settings:
            t0 = time.perf_counter()
            db = build_database(image_dir, args.cache / scene, setting, MAX_FEATURES.get(scene, args.max_features))
            print(f"{scene}/{setting}: input database {time.perf_counter() - t0:.1f} s (0 = cached)", file=sys.stderr)
            work = args.work / scene / setting
            work.mkdir(parents=True, exist_ok=True)

            where = (image_dir, gt, work, mapping, intrinsics, f"{scene}/{setting}")
            m_input = mapped(db, "input", *where)
            out = work / "refined.db"
            t0 = time.perf_counter()
            summary = refine_database(db, image_dir, out, recipe=recipe, overwrite=True, restart=True,
                                      workers=args.workers)
            refine_s = time.perf_counter() - t0
            print(f"{scene}/{setting}: refine {refine_s:.1f} s ({summary.matches_kept}/{summary.matches_in} "
                  f"matches kept)", file=sys.stderr)
            m_refined = mapped(summary.output, "refined", *where)
            oracle_auc = None
            if args.oracle:
                oracle_db, _ = oracle_database(db, work, gt_poses, args.oracle_threshold)
                oracle_auc = mapped(oracle_db, "oracle", *where)["auc"]
            row = end_to_end_row(scene, setting, m_input, refine_s, summary.seconds.get(MATCH_CHECK),
                                 m_refined, oracle_auc)
            rows.append({**row, "refine_stage_seconds": dict(summary.seconds)})
            if args.json:  # partial results survive an interrupted run
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps({"argv": cmd, "recipe": recipe.name, "overrides": args.overrides,
                                                 "threads": args.threads, "workers": args.workers,
                                                 "seconds": time.perf_counter() - t_all, "rows": rows}, indent=2),
                                     encoding="utf-8")
            print(f"{scene}/{setting} done (all: {time.perf_counter() - t_all:.0f} s)", file=sys.stderr)
    wall = time.perf_counter() - t_all
    print(f"recipe {recipe.name} {' '.join('--set ' + o for o in args.overrides)}; incremental mapper, seed 0, "
          f"{args.threads} thread(s), GT intrinsics held fixed (refine_intrinsics=none); refine workers "
          f"{args.workers}; seconds: mapper call / refine_database call (database build not counted); model pose "
          f"AUC over all GT pairs; oracle: matches > {args.oracle_threshold:g} px from their GT epipolar line "
          f"removed; {wall:.0f} s")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
