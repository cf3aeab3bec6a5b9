"""Pose with KNOWN cameras over several mapper seeds: COLMAP alone, the GT oracle and refine variants.

For each scene and COLMAP matching setting (``default``; ``permissive``: SIFT ratio 0.95, no
cross-check) the cached database (``--cache``, the cache of ``bench_accuracy.py``; read only
unless ``--build-missing``) gives these rows:

- ``input``: the database as COLMAP left it;
- ``oracle``: the same database with every stored match farther than ``--oracle-threshold`` px
  (4) from its GT epipolar line removed (:mod:`miho_bench.oracle`): what a perfect
  match filter gives;
- one row per ``--variant``: ``refine_database`` with that recipe / overrides (cached under
  ``--work`` by recipe, overrides and code);
- ``NAME+oracle`` for each variant named by ``--oracle-of``: the oracle applied to that
  variant's output (e.g. the filter's alone: what is left once it removed what it removed).

Every row's database is mapped with each ``--mappers`` mapper (incremental: ``--repeats`` seeds;
global: ``--global-repeats`` seeds) with the GT intrinsics written into the mapped copy and
``refine_intrinsics=none``. One table row per scene / setting / row / mapper: the median over
the seeds of the registered images and of the model pose AUC at 0.5/1/2/5 deg (all GT pairs; the
range over the seeds in brackets), and, from the database alone: the GT-outlier share of the
stored inliers (matches > 4 px from their GT epipolar line; all pairs, and the correct pairs:
median match within 4 px), the correct matches (<= 4 px) and the GT track residual median and
wrong-track share (``keypoint_accuracy``).

    python benchmarks/bench_known_cameras.py [--data ../shared/data] [--work /tmp/bench_known_cameras]
        [--cache /tmp/bench_accuracy] [--scenes ...] [--settings default permissive]
        [--mappers incremental global] [--repeats 3] [--global-repeats 1]
        [--rows input oracle ncc ...] [--recipe mop_miho_ncc] [--set key=value]
        [--variant NAME[:recipe=R,key=value,code=/path/to/checkout]] ... [--oracle-threshold 4]
        [--workers 1] [--threads 1] [--refine-intrinsics none] [--json out.json]

A variant is ``NAME[:key=value,...]`` as in ``bench_accuracy.py`` (``recipe=NAME`` swaps the base
recipe, ``seed=N`` the refine seed: the spread over refine seeds shows how much a reconstruction
moves with a small change of the matches); ``code=PATH`` refines in a subprocess with that
checkout first on ``PYTHONPATH`` (another branch's stage, mapped and measured by this one).
Without ``--variant`` one variant runs: the recipe as given, named after it. ``--rows`` picks rows
by name (piecewise runs); ``--json`` merges into an existing file (a row of the same scene /
setting / row / mapper is replaced), so piecewise runs build one file; ``--table-from`` prints its
tables.

The scene ``demo`` is the built-in demo scene as ``bench_accuracy.py`` renders it into the cache.

``--threads 1`` (default) makes each run deterministic for its seed; the spread then comes
from the seeds alone.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path

from bench_accuracy import (
    DEMO,
    MAX_FEATURES,
    SETTINGS,
    SHARED_SCENES,
    build_database,
    numeric_stats,
    parse_variant,
    scene_inputs,
)

REPO = Path(__file__).resolve().parents[1]
AUCS = (0.5, 1.0, 2.0, 5.0)
TABLE_AUCS = (0.5, 1.0, 2.0)
MAPPERS = ("incremental", "global")
INPUT, ORACLE = "input", "oracle"

# refine in another checkout (``code=``): its colmap_miho on the path, the arguments as JSON
_REFINE_SCRIPT = """
import json, sys
from colmap_miho.pipeline.refine_job import refine_database
from colmap_miho.recipe import load_recipe
a = json.loads(sys.argv[1])
s = refine_database(a["db"], a["images"], a["out"], recipe=load_recipe(a["recipe"], a["overrides"]),
                    overwrite=True, restart=True, workers=a["workers"], seed=a["seed"])
print("REFINE_SUMMARY " + json.dumps({"seconds": s.seconds, "refine_stats": s.refine_stats}, default=str))
"""


# --------------------------------------------------------------------------- databases
def variant_tag(recipe: str | None, overrides: list[str], code: str | None, seed: int = 0) -> str:
    """Cache tag of a refined database: recipe, overrides, code checkout and refine seed."""
    parts = [recipe or "default", *overrides, code or ""] + ([f"seed={seed}"] if seed else [])
    return hashlib.sha1(" ".join(parts).encode()).hexdigest()[:8]


def refined_database(db: Path, image_dir: Path, folder: Path, name: str, recipe: str | None,
                     overrides: list[str], code: str | None, workers: int, seed: int = 0) -> tuple[Path, dict]:
    """``refine_database`` output of ``db`` under ``folder`` (cached by recipe, overrides, code and
    refine seed) and its summary figures (seconds, numeric refine statistics; read back from a side file when
    cached)."""
    tag = variant_tag(recipe, overrides, code, seed)
    out = folder / f"refined_{name}_{tag}.db"
    side = out.with_suffix(".json")
    if out.is_file() and side.is_file():
        return out, json.loads(side.read_text(encoding="utf-8"))
    tmp = out.with_suffix(".tmp.db")
    if code:
        args = {"db": str(db), "images": str(image_dir), "out": str(tmp), "recipe": recipe,
                "overrides": overrides, "workers": workers, "seed": seed}
        env = {**os.environ, "PYTHONPATH": str(Path(code).resolve())}
        proc = subprocess.run([sys.executable, "-c", _REFINE_SCRIPT, json.dumps(args)], env=env, cwd=str(code),
                              capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"refine in {code} failed ({proc.returncode}): {proc.stderr[-2000:]}")
        line = [ln for ln in proc.stdout.splitlines() if ln.startswith("REFINE_SUMMARY ")][-1]
        raw = json.loads(line.split(" ", 1)[1])
    else:
        from colmap_miho.pipeline.refine_job import refine_database
        from colmap_miho.recipe import load_recipe

        s = refine_database(db, image_dir, tmp, recipe=load_recipe(recipe, overrides), overwrite=True, restart=True,
                            workers=workers, seed=seed)
        raw = {"seconds": s.seconds, "refine_stats": s.refine_stats}
    summary = {"refine_seconds": raw["seconds"].get("total"), "seconds": raw["seconds"],
               "refine_stats": numeric_stats(raw.get("refine_stats") or {}), "recipe": recipe,
               "overrides": overrides, "code": None if code is None else Path(code).name, "seed": seed}
    tmp.rename(out)
    side.write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return out, summary


def oracle_database(db: Path, folder: Path, gt_poses: dict, threshold: float) -> tuple[Path, dict]:
    """The GT-oracle copy of ``db`` under ``folder`` (cached) and what it removed."""
    from miho_bench.oracle import write_oracle_database

    out = folder / f"oracle_{threshold:g}px.db"
    side = out.with_suffix(".json")
    if out.is_file() and side.is_file():
        return out, json.loads(side.read_text(encoding="utf-8"))
    tmp = out.with_suffix(".tmp.db")
    tmp.unlink(missing_ok=True)
    stats = write_oracle_database(db, tmp, gt_poses, threshold_px=threshold).to_dict()
    tmp.rename(out)
    side.write_text(json.dumps(stats, indent=2), encoding="utf-8")
    return out, stats


def database_figures(database: Path, gt_poses: dict, threshold: float) -> dict:
    """GT-outlier counts and keypoint accuracy of a database's stored inliers."""
    from colmap_miho.reporting.report import database_keypoint_accuracy, read_database_inliers
    from miho_bench.oracle import gt_epipolar_distances, outlier_counts

    inl = read_database_inliers(database)
    counts = outlier_counts(gt_epipolar_distances(inl.keypoints, inl.matches, gt_poses), threshold)
    return {"gt_outliers": counts.to_dict(), "keypoint_accuracy": database_keypoint_accuracy(inl, gt_poses)}


def map_runs(db: Path, image_dir: Path, gt: Path, folder: Path, seeds: int, mapping, intrinsics) -> list[dict]:
    """Map ``db`` with ``seeds`` seeds (0..seeds-1); one row of figures per run."""
    from colmap_miho.reporting.report import auc_key, build_report
    from colmap_miho.sfm import run_mapping

    rows = []
    for seed in range(seeds):
        res = run_mapping(db, image_dir, folder / f"model_seed{seed}", mapping, seed=seed,
                          intrinsics=intrinsics)
        row = {"seed": seed, "num_reg_images": res.num_reg_images, "num_images": res.num_images,
               "seconds": res.seconds}
        if res.success:
            rep = build_report(reconstruction=res.reconstruction, gt=gt, thresholds=AUCS)
            row.update({auc_key(t): rep["model_pose_auc"][auc_key(t)] for t in AUCS})
            row["mean_reprojection_error"] = rep["reconstruction"]["mean_reprojection_error"]
        else:
            row.update({auc_key(t): 0.0 for t in AUCS})
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- table
def _median_range(values: list[float], pct: bool) -> str:
    """``median [min-max]``; the range only when it shows at the printed precision."""
    def fmt(v: float) -> str:
        return f"{100.0 * v:.1f}" if pct else f"{v:g}"

    lo, med, hi = fmt(min(values)), fmt(statistics.median(values)), fmt(max(values))
    return med if lo == hi else f"{med} [{lo}-{hi}]"


def _row_order(rows: list[dict]) -> list[dict]:
    """The demo, then scenes and settings in first-seen order; within them input, oracle, then
    variants as seen."""
    first: dict = {("scene", DEMO): -1}
    for i, r in enumerate(rows):
        first.setdefault(("scene", r["scene"]), i)
        first.setdefault(("setting", r["scene"], r["setting"]), i)
        first.setdefault(("row", r["row"]), i)
    rank = {INPUT: -2, ORACLE: -1}
    return sorted(rows, key=lambda r: (first[("scene", r["scene"])], first[("setting", r["scene"], r["setting"])],
                                       rank.get(r["row"], first[("row", r["row"])])))


def table(rows: list[dict], mapper: str | None = None) -> str:
    """Markdown table of the rows of one mapper (all when None): medians over the seeds,
    ranges in brackets."""
    from colmap_miho.reporting.report import auc_key

    head = ["scene", "setting", "row", "registered", *[f"AUC@{t:g} (%)" for t in TABLE_AUCS], "AUC@5 (%)",
            "GT-outl. %", "GT-outl. % (correct pairs)", "correct matches", "GT residual med (px)", "wrong tracks %"]
    lines = ["| " + " | ".join(head) + " |", "|---|---|---|" + "---:|" * (len(head) - 3)]
    for r in _row_order([r for r in rows if mapper is None or r.get("mapper") == mapper]):
        runs = r["runs"]
        ka = r.get("keypoint_accuracy", {})
        go = r.get("gt_outliers", {})
        wrong = ka.get("wrong_track_share")
        cells = [r["scene"], r["setting"], r["row"],
                 _median_range([x["num_reg_images"] for x in runs], False) + f"/{runs[0]['num_images']}",
                 *[_median_range([x[auc_key(t)] for x in runs], True) for t in (*TABLE_AUCS, 5.0)],
                 f"{100 * go['outlier_share']:.1f}" if go else "-",
                 f"{100 * go['correct_pair_outlier_share']:.1f}" if go else "-",
                 f"{go['num_correct']}" if go else "-",
                 "-" if ka.get("residual_median_px") is None else f"{ka['residual_median_px']:.3f}",
                 "-" if wrong is None else f"{100 * wrong:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def tables(rows: list[dict]) -> str:
    """One table per mapper present in the rows."""
    out = []
    for mapper in MAPPERS:
        if any(r.get("mapper") == mapper for r in rows):
            out += [f"**{mapper} mapper**", "", table(rows, mapper), ""]
    return "\n".join(out)


def _key(r: dict) -> tuple:
    return r["scene"], r["setting"], r["row"], r["mapper"]


def merge_rows(old: list[dict], new: list[dict]) -> list[dict]:
    """``old`` with the rows of ``new`` replacing those of the same scene / setting / row / mapper
    (in place), the others appended."""
    fresh = {_key(r): r for r in new}
    out = [fresh.pop(_key(r), r) for r in old]
    return out + [r for r in new if _key(r) in fresh]


def portable_path(path: Path, roots: Mapping[str, Path]) -> str:
    """``path`` as ``NAME/relative`` under the first of ``roots`` (name -> folder) that holds
    it, else its file name: results files carry no machine's folders."""
    for name, root in roots.items():
        try:
            return f"{name}/{Path(path).resolve().relative_to(Path(root).resolve()).as_posix()}"
        except ValueError:
            continue
    return Path(path).name


def portable_argv(argv: list[str]) -> list[str]:
    """The command line with each absolute path replaced by its option's name in capitals
    (``--work /x`` -> ``--work WORK``; ``code=/x`` -> ``code=CHECKOUT``)."""
    out: list[str] = []
    for k, tok in enumerate(argv):
        if tok.startswith("/"):
            prev = argv[k - 1] if k else ""
            out.append(prev.lstrip("-").replace("-", "_").upper() if prev.startswith("--") else "PATH")
        else:
            out.append(re.sub(r"code=/[^,]*", "code=CHECKOUT", tok))
    return out


def save_json(path: Path, rows: list[dict], argv: list[str]) -> None:
    """Merge ``rows`` into ``path`` (see :func:`merge_rows`); the command lines are kept in a list."""
    old = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {"rows": [], "commands": []}
    commands = old.get("commands") or ([old["argv"]] if "argv" in old else [])
    if argv not in commands:
        commands.append(argv)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"commands": commands, "rows": merge_rows(old.get("rows", []), rows)}, indent=2),
                   encoding="utf-8")
    tmp.replace(path)


# --------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_known_cameras"),
                    help="refined and oracle databases, models")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_accuracy"),
                    help="database cache (shared with bench_accuracy.py; read only unless --build-missing)")
    ap.add_argument("--build-missing", action="store_true",
                    help="build a database missing from --cache (default: skip that scene/setting)")
    ap.add_argument("--scenes", nargs="+", default=list(SHARED_SCENES))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--mappers", nargs="+", default=["incremental"], choices=list(MAPPERS))
    ap.add_argument("--repeats", type=int, default=3, help="incremental mapping runs per row (seeds 0..N-1)")
    ap.add_argument("--global-repeats", type=int, default=1, help="global mapping runs per row (seeds 0..N-1)")
    ap.add_argument("--recipe", default=None, help="base recipe of the variants (default: the project's)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override for every variant (repeatable)")
    ap.add_argument("--variant", dest="variants", action="append", default=[], metavar="NAME[:K=V,K=V]",
                    help="a refine variant (repeatable); 'recipe=NAME' swaps the base recipe, 'code=PATH' refines "
                         "with another checkout's code")
    ap.add_argument("--rows", nargs="+", default=None,
                    help="run only these rows (input, oracle, variant names; default all)")
    ap.add_argument("--oracle-of", nargs="+", default=[], metavar="VARIANT",
                    help="also a row NAME+oracle per variant named: the oracle applied to its output")
    ap.add_argument("--oracle-threshold", type=float, default=4.0,
                    help="GT epipolar distance (px) above which the oracle removes a match, and the "
                         "GT-outlier threshold of the counts")
    ap.add_argument("--workers", type=int, default=1, help="refine_database workers (default 1)")
    ap.add_argument("--threads", type=int, default=1, help="mapper threads (default 1: deterministic per seed)")
    ap.add_argument("--refine-intrinsics", default="none", choices=["all", "default", "none"])
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--json", type=Path, default=None,
                    help="merge every row into this JSON file (rows of the same scene/setting/row/mapper replaced)")
    ap.add_argument("--table-from", type=Path, default=None, metavar="JSON",
                    help="print the tables of an earlier run's --json file and exit")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.global_repeats < 1:
        ap.error("--repeats and --global-repeats must be >= 1")
    if not args.oracle_threshold > 0:
        ap.error("--oracle-threshold must be > 0")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.table_from:
        print(tables(json.loads(args.table_from.read_text(encoding="utf-8"))["rows"]))
        return 0

    try:
        parsed = [parse_variant(v) for v in args.variants]
    except ValueError as exc:
        ap.error(str(exc))
    variants = []  # (name, recipe, overrides, code, refine seed)
    for name, recipe, ov in parsed or [(args.recipe or "recipe", None, [])]:
        if name == ORACLE:
            ap.error("--variant needs a name other than 'oracle'")
        code = next((o.partition("=")[2].strip() for o in ov if o.partition("=")[0].strip() == "code"), None)
        seed = next((o.partition("=")[2].strip() for o in ov if o.partition("=")[0].strip() == "seed"), "0")
        if not seed.isdigit():
            ap.error(f"--variant {name}: seed must be a non-negative integer, got {seed!r}")
        ov = [o for o in ov if o.partition("=")[0].strip() not in ("code", "seed")]
        variants.append((name, recipe or args.recipe, ov, code, int(seed)))
    if len({v[0] for v in variants}) != len(variants):
        ap.error("--variant names must differ")
    wanted = set(args.rows) if args.rows else None

    import pycolmap

    from colmap_miho.recipe import load_recipe
    from colmap_miho.reporting.compare import gt_intrinsics
    from colmap_miho.reporting.gt_model import load_gt_poses

    pycolmap.logging.minloglevel = 1
    common = [f"mapping.num_threads={args.threads}", f"mapping.refine_intrinsics={args.refine_intrinsics}"]
    for _name, recipe, ov, code, _seed in variants:  # a bad recipe or key fails here, before any work
        if code is None:  # another checkout's recipe keys are its own: checked when it refines
            load_recipe(recipe, [*args.overrides, *ov, *common])
    mapping = load_recipe(args.recipe, [*args.overrides, *common]).mapping
    cmd = portable_argv(sys.argv[1:] if argv is None else list(argv))
    t_all = time.perf_counter()
    rows: list[dict] = []
    for scene in args.scenes:
        root = args.cache / DEMO / "scene" if scene == DEMO else args.data / scene
        if scene == DEMO and not (root / "gt_model").is_dir() and not args.build_missing:
            print(f"skip {scene}: not rendered under {root} (--build-missing renders it)", file=sys.stderr)
            continue
        found = scene_inputs(scene, args.data, args.cache)  # the demo as bench_accuracy.py renders it
        if found is None:
            print(f"skip {scene}: no images/ or gt_model/ under {root}", file=sys.stderr)
            continue
        image_dir, gt = found
        gt_poses, intrinsics = load_gt_poses(gt), gt_intrinsics(gt)
        for setting in args.settings:
            cached = args.cache / scene / setting / "database.db"
            if not cached.is_file() and not args.build_missing:
                print(f"skip {scene}/{setting}: no {cached} (--build-missing builds it)", file=sys.stderr)
                continue
            db = build_database(image_dir, args.cache / scene, setting, MAX_FEATURES.get(scene, args.max_features))
            work = args.work / scene / setting
            work.mkdir(parents=True, exist_ok=True)
            plan = [(INPUT, None), (ORACLE, None), *[(v[0], v) for v in variants]]
            plan += [(f"{v[0]}+oracle", v) for v in variants if v[0] in args.oracle_of]
            for row_name, variant in plan:
                if wanted is not None and row_name not in wanted:
                    continue
                t0 = time.perf_counter()
                if row_name == INPUT:
                    database, info = db, {}
                elif row_name == ORACLE:
                    database, stats = oracle_database(db, work, gt_poses, args.oracle_threshold)
                    info = {"oracle": stats}
                else:
                    name, recipe, ov, code, seed = variant
                    database, info = refined_database(db, image_dir, work, name, recipe,
                                                      [*args.overrides, *ov, *common], code, args.workers, seed)
                    if row_name.endswith("+oracle"):  # the oracle applied to the variant's output
                        database, stats = oracle_database(database, work / row_name, gt_poses, args.oracle_threshold)
                        info = {**info, "oracle": stats}
                figures = database_figures(database, gt_poses, args.oracle_threshold)
                for mapper in args.mappers:
                    from dataclasses import replace

                    seeds = args.repeats if mapper == "incremental" else args.global_repeats
                    runs = map_runs(database, image_dir, gt, work / row_name / mapper, seeds,
                                    replace(mapping, mapper=mapper), intrinsics)
                    rows.append({"scene": scene, "setting": setting, "row": row_name, "mapper": mapper,
                                 "database": portable_path(database, {"WORK": args.work, "CACHE": args.cache}),
                                 **info, **figures, "runs": runs})
                    if args.json:  # partial results survive an interrupted run
                        save_json(args.json, rows, cmd)
                print(f"{scene}/{setting}/{row_name} done in {time.perf_counter() - t0:.0f} s "
                      f"(all: {time.perf_counter() - t_all:.0f} s)", file=sys.stderr)
    wall = time.perf_counter() - t_all
    print(f"GT intrinsics, refine_intrinsics={args.refine_intrinsics}; median over the seeds (incremental "
          f"{args.repeats}, global {args.global_repeats}; {args.threads} thread(s)), range in brackets; model pose "
          f"AUC over all GT pairs; GT-outl. = stored inliers > {args.oracle_threshold:g} px from their GT epipolar "
          f"line (correct pairs: median match within it), correct matches = the others; GT residual = median "
          f"residual of the stored inliers' tracks triangulated with the GT cameras (tracks <= 4 px), wrong = "
          f"tracks > 4 px; {wall:.0f} s")
    print(tables(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
