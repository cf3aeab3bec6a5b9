"""What the match check gives back of the matches the filter removed, judged by the GT.

For each scene and COLMAP matching setting (the cached databases of ``bench_accuracy.py``),
``refine_database`` runs with the default recipe (``--set`` overrides) in this process; the
check's candidates (the matches the filter removed) and what it restored are captured and
judged by their GT epipolar distance (``--threshold`` px, 4: a GT-correct match lies within).
Printed per database: the candidates and how many are GT-correct, the restored matches and how
many of them are GT-wrong, the pairs the filter left without matches that hold at least
``--pair-min`` GT-correct candidates, and how many of those came back.

    python benchmarks/bench_restore.py [--scenes ...] [--settings default permissive]
        [--cache /tmp/bench_accuracy] [--work /tmp/bench_restore] [--set key=value] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import SETTINGS, SHARED_SCENES, build_database, scene_inputs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def run_one(db: Path, images: Path, out: Path, overrides: list[str]) -> tuple[dict, dict, set, dict]:
    """Refine ``db``; (candidates, restored masks, the pairs the check was given, summary's
    match-check stats)."""
    import colmap_miho.pipeline.match_check as stage
    from colmap_miho.pipeline.run import refine_database
    from colmap_miho.recipe import load_recipe

    captured: dict = {}
    original = stage.judge_in_rounds

    def spy(matches, estimator, cfg, candidates=None):
        d = original(matches, estimator, cfg, candidates)
        captured.update(candidates=dict(candidates or {}), restored=dict(d.restored), kept=set(matches))
        return d

    stage.judge_in_rounds = spy
    try:
        s = refine_database(db, images, out, recipe=load_recipe(None, overrides), overwrite=True, restart=True,
                            workers=1)
    finally:
        stage.judge_in_rounds = original
    return (captured.get("candidates", {}), captured.get("restored", {}), captured.get("kept", set()),
            s.match_check or {})


def keypoints_and_names(db: Path) -> tuple[dict[int, np.ndarray], dict[int, str]]:
    from colmap_miho.adapters.database import ColmapDatabase

    d = ColmapDatabase(db)
    try:
        names = {im.image_id: im.name for im in d.images()}
        kp = {i: d.keypoints(i) for i in names}
    finally:
        d.close()
    return kp, names


def gt_distances(pairs: dict, kp, names, gt) -> dict:
    from miho_bench.oracle import pair_distances

    out = {}
    for (i, j), m in pairs.items():
        if names[i] in gt and names[j] in gt and len(m):
            m = np.asarray(m, np.int64)
            out[(i, j)] = pair_distances(gt[names[i]], gt[names[j]], kp[i][m[:, 0]], kp[j][m[:, 1]])
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_accuracy"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_restore"))
    ap.add_argument("--scenes", nargs="+", default=["demo", *SHARED_SCENES])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--threshold", type=float, default=4.0)
    ap.add_argument("--pair-min", type=int, default=8)
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from colmap_miho.reporting.gt_model import load_gt_poses

    rows = []
    for scene in args.scenes:
        inputs = scene_inputs(scene, args.data, args.cache)
        if inputs is None:
            print(f"{scene}: no data, skipped")
            continue
        images, gt_dir = inputs
        gt = load_gt_poses(gt_dir)
        for setting in args.settings:
            db = build_database(images, args.cache / scene, setting, args.max_features)
            work = args.work / scene / setting
            work.mkdir(parents=True, exist_ok=True)
            cand, restored, kept, mc = run_one(db, images, work / "refined.db", args.overrides)
            kp, names = keypoints_and_names(db)
            dist = gt_distances(cand, kp, names, gt)
            correct = {p: d <= args.threshold for p, d in dist.items()}
            n_cand = sum(len(m) for m in cand.values())
            n_corr = sum(int(c.sum()) for c in correct.values())
            n_rest = sum(int(r.sum()) for r in restored.values())
            n_rest_wrong = sum(int((r & ~correct[p]).sum()) for p, r in restored.items() if p in correct)
            n_rest_corr = sum(int((r & correct[p]).sum()) for p, r in restored.items() if p in correct)
            # pairs the filter left without matches that hold enough GT-correct ones
            lost = [p for p in cand if p in correct and p not in kept and int(correct[p].sum()) >= args.pair_min]
            row = {"scene": scene, "setting": setting, "candidates": n_cand, "candidates_correct": n_corr,
                   "restored": n_rest, "restored_correct": n_rest_corr, "restored_wrong": n_rest_wrong,
                   "pairs_restored": len(restored), "pairs_revived": mc.get("pairs_revived", 0),
                   "seconds_restoring": sum(r.get("restoring", 0.0) for r in mc.get("round_seconds", [])),
                   "check_seconds": mc.get("seconds", 0.0), "pairs_dropped_correct": len(lost),
                   "pairs_dropped_correct_revived": sum(1 for p in lost if p in restored)}
            rows.append(row)
            print(json.dumps(row))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
