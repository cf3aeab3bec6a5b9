"""What the match check removes and what it costs with each way of building its global estimate.

For each scene, COLMAP matching setting and SIFT budget, the database is built once (as
``bench_accuracy.py`` builds it, cached under ``--cache/<features>``), ``refine_database`` runs
with the default recipe up to the match check and keeps the check's input (the filtered pair
graph, as ``bench_hinge.py``); the check then runs on it once per ``--variant`` and per
``--seeds`` seed (the match check's seed: the global mapper's and the track sample's), with
pycolmap's global mapper on ``--threads`` threads. Each match is judged against its GT epipolar
line (a GT outlier lies more than 4 px from it). Printed per database, variant and seed: the
GT-correct matches removed, the GT-wrong ones removed, the rounds, the stage's process CPU
seconds and its split (mapper, the pairs' own rotations, the hinge search); at the end, per
database, each variant's median over the seeds.

    python benchmarks/bench_match_check_estimate.py [--scenes ...] [--settings default permissive]
        [--features 4096 8192] [--seeds 0 1 2] [--cache /tmp/bench_hinge] [--threads 1]
        [--variant NAME[:key=value,...]] ... [--json out.json]

A variant is a name and ``MatchCheckConfig`` fields (``all:estimate_matches_per_image=0`` is the
estimate from every match); without ``--variant``: ``default`` (the project's settings) and
``all`` (``estimate_matches_per_image=0,pair_rotation_matches=0``: the estimate before the
sample). The scene ``demo`` is the built-in demo scene (2048 SIFT).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import MAX_FEATURES, build_database, scene_inputs  # noqa: E402
from bench_hard_pairs import parse_variant  # noqa: E402
from bench_hinge import database_arguments, gt_labels, stage_input  # noqa: E402

from miho_bench.variants import configured  # noqa: E402


def run_check(db, matches, labels, fields: dict, seed: int, threads: int) -> dict:
    from colmap_miho.sfm.global_estimate import GlobalEstimator
    from colmap_miho.verification import MatchCheckConfig, judge_in_rounds

    cfg = configured(MatchCheckConfig, mode="remove", **fields)
    cpu = time.process_time()
    d = judge_in_rounds(matches, GlobalEstimator(src=db, config=cfg, seed=seed, num_threads=threads), cfg)
    cpu = time.process_time() - cpu
    pairs = sorted(matches)
    ok = np.concatenate([labels[p] for p in pairs])
    failed = np.concatenate([d.failed.get(p, np.zeros(len(matches[p]), bool)) for p in pairs])
    parts: dict[str, float] = {}
    for r in d.seconds:
        for k, v in r.items():
            parts[k] = parts.get(k, 0.0) + v
    return {"used": d.used, "rounds": d.rounds, "correct_removed": round(100 * float(failed[ok].mean()), 2),
            "wrong_removed": round(100 * float(failed[~ok].mean()), 1) if (~ok).any() else 0.0,
            "cpu_s": round(cpu, 2), "mapper_s": round(parts.get("mapper", 0.0), 2),
            "pair_rotations_s": round(parts.get("pair_rotations", 0.0), 2),
            "hinge_s": round(parts.get("hinge", 0.0), 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    database_arguments(ap)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="root seeds (the match check's seed)")
    ap.add_argument("--threads", type=int, default=1, help="global mapper threads")
    ap.add_argument("--variant", dest="variants", action="append", default=[])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    before = "all:estimate_matches_per_image=0,pair_rotation_matches=0"
    variants = [parse_variant(v) for v in (args.variants or ["default", before])]
    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.reporting.gt_model import load_gt_poses

    rows = []
    print("| scene | matching | SIFT | variant | seed | rounds | correct removed % | wrong removed % | stage CPU s | "
          "mapper s | pairs' rotations s | hinge search s |")
    print("|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for scene in args.scenes:
        inputs = scene_inputs(scene, args.data, args.cache)
        if inputs is None:
            logging.warning("skipped %s: not in %s", scene, args.data)
            continue
        image_dir, gt_dir = inputs
        gt = load_gt_poses(gt_dir)
        for setting in args.settings:
            for features in ([MAX_FEATURES[scene]] if scene in MAX_FEATURES else args.features):
                database = build_database(image_dir, args.cache / str(features) / scene, setting, features)
                matches = stage_input(database, image_dir, 0)
                with tempfile.TemporaryDirectory(prefix="bench-mce-") as tmp:
                    shutil.copyfile(database, Path(tmp) / "db.db")  # the check only reads; opening migrates a copy
                    with ColmapDatabase(Path(tmp) / "db.db") as db:
                        labels = gt_labels(db, matches, gt)
                        for name, fields in variants:
                            for seed in args.seeds:
                                r = {"scene": scene, "setting": setting, "features": features, "variant": name,
                                     "seed": seed, **run_check(db, matches, labels, fields, seed, args.threads)}
                                rows.append(r)
                                print(f"| {scene} | {setting} | {features} | {name} | {seed} | {r['rounds']} | "
                                      f"{r['correct_removed']:.2f} | {r['wrong_removed']:.1f} | {r['cpu_s']} | "
                                      f"{r['mapper_s']} | {r['pair_rotations_s']} | {r['hinge_s']} |", flush=True)
                                if args.json:
                                    args.json.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    print()
    print(summary(rows))
    return 0


def summary(rows: list[dict]) -> str:
    """One line per database: each variant's median over the seeds (the range in brackets)."""
    import statistics

    def cell(values: list[float], fmt: str) -> str:
        med = statistics.median(values)
        lo, hi = min(values), max(values)
        return f"{med:{fmt}}" if lo == hi else f"{med:{fmt}} [{lo:{fmt}}-{hi:{fmt}}]"

    names = list(dict.fromkeys(r["variant"] for r in rows))
    out = ["| scene | matching | SIFT | " + " | ".join(f"{n}: correct removed % / wrong removed % / stage CPU s"
                                                   for n in names) + " |",
           "|---|---|---:|" + "---|" * len(names)]
    for key in dict.fromkeys((r["scene"], r["setting"], r["features"]) for r in rows):
        cells = []
        for n in names:
            rs = [r for r in rows if (r["scene"], r["setting"], r["features"]) == key and r["variant"] == n]
            cells.append(" / ".join([cell([r["correct_removed"] for r in rs], ".2f"),
                                     cell([r["wrong_removed"] for r in rs], ".1f"),
                                     cell([r["cpu_s"] for r in rs], ".1f")]) if rs else "-")
        out.append(f"| {key[0]} | {key[1]} | {key[2]} | " + " | ".join(cells) + " |")
    return "\n".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
