"""Pair check: wrong pairs found and correct pairs kept, on synthetic doppelganger scenes with
exact GT and on the shared scenes and the demo under their GT cameras.

Synthetic scenes (``tests/doppelganger.py``): a wall with two identical facades; the pairs
whose matches join one facade to the other are wrong by construction. Real scenes: the
databases of ``benchmarks/bench_accuracy.py`` (COLMAP SIFT, exhaustive matching, ``default``
and ``permissive`` settings, cached under ``--work``), filtered by ``refine`` (MOP+MiHo, no
refinement: the pair check's input); a pair is wrong when the median symmetric distance of its
kept matches to the GT epipolar lines exceeds ``--wrong-px`` (4 px). Counted: wrong pairs found
(recall), correct pairs removed, images that lose their last pair, the check's time.

    python benchmarks/bench_pair_check.py [--data ../shared/data] [--work /tmp/bench_accuracy]
        [--scenes demo middlebury_temple_sparse_ring strecha_fountain_p11 strecha_entry_p10]
        [--settings default permissive] [--synthetic-seeds 0 1 2 3 4] [--set key=value ...]
        [--cost] [--json out.json]

``--set`` overrides ``pair_check`` fields (e.g. ``--set trust_iterations=0``). ``--cost``
also times a full ``refine`` of fountain (default setting) with the check on, and reports the
check's share of the refine stage's time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the synthetic doppelganger scenes

from bench_accuracy import DEMO, MAX_FEATURES, SETTINGS, SHARED_SCENES, build_database, scene_inputs  # noqa: E402


def pair_config(overrides: list[str]):
    from colmap_miho.recipe import load_recipe

    return load_recipe(None, ["pair_check.enabled=true"] + [f"pair_check.{o}" for o in overrides]).pair_check


def score(result, truth: dict, images: set) -> dict:
    """Counts of a :class:`PairCheckResult` against ``truth`` (pair -> wrong)."""
    wrong = {p for p, w in truth.items() if w}
    found = set(result.wrong)
    degree_before: dict = {}
    degree_after: dict = {}
    for (i, j) in truth:
        for k in (i, j):
            degree_before[k] = degree_before.get(k, 0) + 1
            degree_after[k] = degree_after.get(k, 0) + ((i, j) not in found)
    return {"pairs": len(truth), "wrong": len(wrong), "found": len(found & wrong),
            "recall": len(found & wrong) / len(wrong) if wrong else None,
            "correct_removed": len(found - wrong), "correct": len(truth) - len(wrong),
            "images_isolated": sum(1 for k in degree_before if degree_after[k] == 0),
            "triangles": result.triangles, "triangles_broken": result.triangles_broken}


def synthetic_rows(seeds: list[int], cfg) -> list[dict]:
    """One row per regime of the synthetic scenes, summed over ``seeds``: few doppelganger
    pairs (20% of the facade-A / facade-B camera pairs fooled) and many (60%: the wrong pairs
    form groups that agree with each other)."""
    from doppelganger import make_doppelganger_scene

    from colmap_miho.verification import check_pairs

    rows = []
    for label, fooled in (("few", 0.2), ("many", 0.6)):
        total: dict = {}
        cpu = 0.0
        for seed in seeds:
            scene = make_doppelganger_scene(seed=seed, fooled_prob=fooled)
            t0 = time.process_time()
            result = check_pairs(scene.matches, scene.keypoints, cfg)
            cpu += time.process_time() - t0
            for k, v in score(result, scene.wrong, set(scene.keypoints)).items():
                if k != "recall":
                    total[k] = total.get(k, 0) + v
        total["recall"] = total["found"] / total["wrong"] if total["wrong"] else None
        rows.append({"scene": f"synthetic, {label} doppelgangers ({len(seeds)} seeds)", "setting": "-",
                     "seconds_cpu": cpu / max(len(seeds), 1), **total})
    return rows


def gt_truth(database: Path, gt: dict, wrong_px: float) -> tuple[dict, dict, dict, dict]:
    """(matches by id pair, keypoints by id, truth by id pair, median GT distance by id pair)."""
    import tempfile

    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.adapters.safety import read_copy
    from colmap_miho.reporting.keypoint_accuracy import fundamental_from_poses, symmetric_epipolar_distance

    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "db.db"
        read_copy(database, copy)
        with ColmapDatabase(copy) as db:
            names = {r.image_id: r.name for r in db.images()}
            keypoints = {i: db.keypoints(i) for i in names}
            matches = {(p.image_id1, p.image_id2): db.matches(p.image_id1, p.image_id2, "verified").astype(np.int64)
                       for p in db.pairs("verified")}
    truth, dist = {}, {}
    for (i, j), m in matches.items():
        a, b = gt[names[i]], gt[names[j]]
        F = fundamental_from_poses(a.K, a.R, a.t, b.K, b.R, b.t)
        d = float(np.median(symmetric_epipolar_distance(F, keypoints[i][m[:, 0]], keypoints[j][m[:, 1]])))
        truth[(i, j)], dist[(i, j)] = d > wrong_px, d
    return matches, keypoints, truth, dist


def filtered_database(db: Path, image_dir: Path, folder: Path) -> Path:
    """``refine`` with MOP+MiHo and no refinement (cached): the pair check's input."""
    from colmap_miho.pipeline.run import refine_database
    from colmap_miho.recipe import load_recipe

    out = folder / "pair_check_input.db"
    if not out.is_file():
        refine_database(db, image_dir, out, recipe=load_recipe(None, ["pipeline.refine=false"]), overwrite=True,
                        restart=True, workers=1, seed=0)
    return out


def real_rows(args, cfg) -> list[dict]:
    from colmap_miho.reporting.gt_model import load_gt_poses
    from colmap_miho.verification import check_pairs

    rows = []
    for scene in args.scenes:
        found = scene_inputs(scene, args.data, args.work)
        if found is None:
            print(f"skip {scene}: not under {args.data}", file=sys.stderr)
            continue
        image_dir, gt_dir = found
        gt = load_gt_poses(gt_dir)
        for setting in args.settings:
            db = build_database(image_dir, args.work / scene, setting, MAX_FEATURES.get(scene, args.max_features))
            filtered = filtered_database(db, image_dir, db.parent)
            matches, keypoints, truth, dist = gt_truth(filtered, gt, args.wrong_px)
            t0 = time.process_time()
            result = check_pairs(matches, keypoints, cfg)
            cpu = time.process_time() - t0
            row = {"scene": scene, "setting": setting, "seconds_cpu": cpu, **score(result, truth, set(keypoints))}
            row["removed"] = [{"pair": list(p), "gt_median_px": round(dist[p], 2),
                               **result.verdicts[p].to_dict()} for p in result.wrong]
            row["wrong_pairs"] = [{"pair": list(p), "gt_median_px": round(dist[p], 2),
                                   **result.verdicts[p].to_dict()} for p, w in truth.items() if w]
            rows.append(row)
            print(f"{scene}/{setting}: {row['found']}/{row['wrong']} wrong found, "
                  f"{row['correct_removed']} correct removed, {cpu:.2f} s CPU", file=sys.stderr)
    return rows


def cost_row(args, cfg) -> dict:
    """Full refine of fountain (default setting) with the check on: the check's share of the
    refine stage's time (wall, both from the run's summary)."""
    from colmap_miho.pipeline.run import refine_database
    from colmap_miho.recipe import load_recipe

    scene = "strecha_fountain_p11"
    found = scene_inputs(scene, args.data, args.work)
    if found is None:
        return {}
    image_dir, _ = found
    db = build_database(image_dir, args.work / scene, "default", args.max_features)
    rec = dataclasses.replace(load_recipe(None), pair_check=cfg)
    s = refine_database(db, image_dir, db.parent / "pair_check_cost.db", recipe=rec, overwrite=True,
                        restart=True, workers=args.workers, seed=0)
    check, refine = s.seconds.get("pair_check", 0.0), s.seconds.get("refine", 0.0)
    return {"scene": scene, "pair_check_s": check, "refine_s": refine,
            "share_of_refine": check / refine if refine else None}


def table(rows: list[dict]) -> str:
    lines = ["| scene | setting | pairs | wrong (GT) | wrong found | correct removed | images isolated "
             "| triangles (broken) | check CPU s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['setting']} | {r['pairs']} | {r['wrong']} | {r['found']} "
                     f"| {r['correct_removed']} of {r['correct']} | {r['images_isolated']} "
                     f"| {r['triangles']} ({r['triangles_broken']}) | {r['seconds_cpu']:.3f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_accuracy"), help="cache of scenes and databases")
    ap.add_argument("--scenes", nargs="*", default=[DEMO, *SHARED_SCENES])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--synthetic-seeds", nargs="*", type=int, default=list(range(8)))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="pair_check field override (repeatable)")
    ap.add_argument("--wrong-px", type=float, default=4.0, help="GT median epipolar distance of a wrong pair")
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cost", action="store_true", help="time a full refine of fountain with the check")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None, help="write the table (and the cost) as Markdown")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    import pycolmap

    pycolmap.logging.minloglevel = 2
    cfg = pair_config(args.overrides)
    rows = (synthetic_rows(args.synthetic_seeds, cfg) if args.synthetic_seeds else []) + real_rows(args, cfg)
    print(table(rows))
    out = {"config": {k: str(v) for k, v in dataclasses.asdict(cfg).items()}, "rows": rows}
    if args.cost:
        out["cost"] = cost_row(args, cfg)
        print(f"cost on fountain: {json.dumps(out['cost'])}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    if args.md:
        command = "python benchmarks/bench_pair_check.py " + " ".join(argv if argv is not None else sys.argv[1:])
        text = f"Produced by `{command}`.\n\n{table(rows)}\n"
        if out.get("cost"):
            c = out["cost"]
            text += (f"\nCost on {c['scene']} (default matching, full `refine`, wall seconds from its summary): "
                     f"pair check {c['pair_check_s']:.2f} s, refine stage {c['refine_s']:.2f} s "
                     f"({100 * c['share_of_refine']:.0f}%).\n")
        args.md.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
