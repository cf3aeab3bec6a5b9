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
        [--plant N]

``--plant N`` is the repeated-structure stress: N wrong matches per pair are added to a copy of
the input (its matches and inliers), each within 2 px of its GT epipolar line and at least 20 px
from where the point truly is in the second image (the point triangulated with the GT cameras
from a match confirmed in a third image). The row then says how many of them the filter removed
(offered to the check) and how many the check restored (it should be none).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import SETTINGS, SHARED_SCENES, build_database, scene_inputs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def run_one(db: Path, images: Path, out: Path, overrides: list[str]) -> tuple[dict, dict, set, dict]:
    """Refine ``db``; (candidates, restored masks, the pairs the check was given, summary's
    match-check stats)."""
    import colmap_miho.pipeline.match_check_stage as stage
    from colmap_miho.pipeline.refine_job import refine_database
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


def plant(db: Path, out: Path, gt, names_gt_kp, per_pair: int, seed: int = 0) -> dict[tuple[int, int], set]:
    """A copy of ``db`` at ``out`` with ``per_pair`` wrong matches on the GT epipolar line added to
    each pair of two GT images; returns the planted ``(k1, k2)`` per pair."""
    import pycolmap

    from colmap_miho.geometry import symmetric_epipolar_distance

    kp, names = names_gt_kp
    cams = {i: gt[n] for i, n in names.items() if n in gt}
    h = pycolmap.Database.open(str(db))
    try:
        pair_ids, tvgs = h.read_two_view_geometries()
        pairs = {tuple(int(x) for x in pycolmap.pair_id_to_image_pair(p)): np.asarray(t.inlier_matches, np.int64)
                 for p, t in zip(pair_ids, tvgs, strict=True)}
    finally:
        h.close()
    # the 3D point of every keypoint that a GT-exact match (<= 1 px) confirmed in a third image holds
    ends: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for (i, j), m in pairs.items():
        if i in cams and j in cams and len(m):
            d = symmetric_epipolar_distance(_F(cams[i], cams[j]), kp[i][m[:, 0]], kp[j][m[:, 1]])
            for a, b in m[d <= 1.0].tolist():
                ends.setdefault((i, a), []).append((j, b))
                ends.setdefault((j, b), []).append((i, a))
    points = {}
    for (i, a), others in ends.items():
        if len(others) < 2:
            continue
        (k, c), (q, e) = others[0], others[1]
        X = _triangulate(cams[i], kp[i][a], cams[k], kp[k][c])
        if X is not None and np.linalg.norm(_project(cams[q], X) - kp[q][e]) <= 2.0:
            points[(i, a)] = X
    rng = np.random.default_rng(seed)
    planted: dict[tuple[int, int], set] = {}
    shutil.copyfile(db, out)
    h = pycolmap.Database.open(str(out))
    try:
        pair_ids, tvgs = h.read_two_view_geometries()
        for p, tvg in zip(pair_ids, tvgs, strict=True):
            i, j = (int(x) for x in pycolmap.pair_id_to_image_pair(p))
            if i not in cams or j not in cams:
                continue
            F = _F(cams[i], cams[j])
            m = np.asarray(tvg.inlier_matches, np.int64).reshape(-1, 2)
            have = {tuple(r) for r in m.tolist()}
            new = []
            for a in rng.permutation([a for (im, a) in points if im == i]).tolist():
                truth = _project(cams[j], points[(i, a)])
                dist = symmetric_epipolar_distance(F, np.repeat(kp[i][a:a + 1], len(kp[j]), 0), kp[j])
                far = np.linalg.norm(kp[j] - truth, axis=1)
                cand = np.flatnonzero((dist <= 2.0) & (far >= 20.0))
                if len(cand):
                    b = int(cand[np.argmin(far[cand])])
                    if (a, b) not in have:
                        new.append((a, b))
                        have.add((a, b))
                if len(new) >= per_pair:
                    break
            if not new:
                continue
            both = np.concatenate([m, np.asarray(new, np.int64)]).astype(np.uint32)
            h.delete_matches(i, j)
            h.write_matches(i, j, both)
            tvg.inlier_matches = both
            h.update_two_view_geometry(i, j, tvg)
            planted[(i, j)] = set(new)
    finally:
        h.close()
    return planted


def planted_count(cand: dict, selected: dict, planted: dict) -> int:
    """The candidates ``selected`` (pair -> bool mask) that are planted matches."""
    return sum(sum(1 for r in np.flatnonzero(sel) if tuple(cand[p][r].tolist()) in planted.get(p, ()))
               for p, sel in selected.items())


def _F(c1, c2) -> np.ndarray:
    from colmap_miho.geometry import fundamental_from_poses

    return fundamental_from_poses(c1.K, c1.R, c1.t, c2.K, c2.R, c2.t)


def _project(cam, X) -> np.ndarray:
    y = cam.K @ (cam.R @ X + cam.t)
    return y[:2] / y[2]


def _triangulate(c1, x1, c2, x2):
    """Linear triangulation of pixels ``x1``, ``x2`` with GT cameras (None behind either)."""
    P1 = c1.K @ np.column_stack([c1.R, c1.t])
    P2 = c2.K @ np.column_stack([c2.R, c2.t])
    A = np.stack([x1[0] * P1[2] - P1[0], x1[1] * P1[2] - P1[1], x2[0] * P2[2] - P2[0], x2[1] * P2[2] - P2[1]])
    X = np.linalg.svd(A)[2][-1]
    X = X[:3] / X[3]
    return X if (c1.R @ X + c1.t)[2] > 0 and (c2.R @ X + c2.t)[2] > 0 else None


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
    ap.add_argument("--plant", type=int, default=0, help="wrong matches on the epipolar line per pair (stress)")
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
            kp, names = keypoints_and_names(db)
            planted: dict = {}
            if args.plant:
                planted = plant(db, work / "planted.db", gt, (kp, names), args.plant)
                db = work / "planted.db"
            cand, restored, kept, mc = run_one(db, images, work / "refined.db", args.overrides)
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
            if args.plant:
                offered = planted_count(cand, {p: np.ones(len(m), bool) for p, m in cand.items()}, planted)
                row.update(planted=sum(len(v) for v in planted.values()), planted_removed_by_filter=offered,
                           planted_restored=planted_count(cand, restored, planted))
            rows.append(row)
            print(json.dumps(row))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
