"""What the match check's hinge search finds on real databases, and what it costs.

For each scene, COLMAP matching setting and SIFT budget, the database is built once (as
``bench_accuracy.py`` builds it, cached under ``--cache/<features>``), ``refine_database`` runs
with the default recipe up to the match check, and the check's input (the filtered pair graph) is
kept; the check then runs on it twice, with and without the hinge search
(``MatchCheckConfig.hinges``), with pycolmap's global mapper on ``--threads`` threads as ``refine``
runs it. Each match is judged against its GT epipolar line (a GT outlier lies more than 4 px
from it). Printed per database: the pairs and matches judged; the hinge search's findings (a
mode not confirmed by 3D points, a hinge and the arbiter's verdict and action); the GT-correct
matches the check removes with and without the hinge search, and the wrong ones; the estimate's
largest GT rotation error after one global alignment; the ROC AUC of the arbiter's score (each
pair's own coverage under the first estimate) for telling GT-correct pairs from GT-wrong ones;
the stage's seconds with and without the search, and the search's own.

    python benchmarks/bench_hinge.py [--scenes ...] [--settings default permissive]
        [--features 4096 8192] [--seeds 0] [--cache /tmp/bench_hinge] [--threads 2] [--json out.json]
        [--hinge-by-construction CUT KEEP] [--check-seed N] [--sample-every-component]

``--sample-every-component`` makes the global estimate's track sample take the components that
hold two keypoints of one image too (no track counts as repeating an image): on castle-P19
8192 SIFT permissive with ``--check-seed 1`` the mapper then turns four images on the repeated
facade against the rest, a hinge on real data.

``--hinge-by-construction CUT KEEP`` makes a hinge on a real database: of the GT-correct pairs
between the images named before ``CUT`` (in name order) and the others, only the ``KEEP`` with
the most matches stay in the check's input (the wrong ones all stay), so that the wrong pairs
outnumber the correct ones across.

The scene ``demo`` is the built-in demo scene (2048 SIFT, as ``bench_accuracy.py``).
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

from bench_accuracy import DEMO, MAX_FEATURES, SETTINGS, SHARED_SCENES, build_database, scene_inputs  # noqa: E402

from miho_bench.variants import variant  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
GT_THRESHOLD_PX = 4.0


class _Captured(Exception):
    """Raised by the patched stage once it holds its input."""


def stage_input(database: Path, image_dir: Path, seed: int) -> dict[tuple[int, int], np.ndarray]:
    """The match check's input of ``refine_database`` with the default recipe and ``seed``:
    the filtered pair graph (the run stops there; the database is only read)."""
    import colmap_miho.pipeline.match_check_stage as stage
    from colmap_miho import refine_database

    held: dict = {}
    original = stage.judge_in_rounds

    def grab(matches, estimator, cfg, candidates=None):
        held.update(matches)
        raise _Captured

    stage.judge_in_rounds = grab
    tmp = Path(tempfile.mkdtemp(prefix="bench-hinge-"))
    try:
        refine_database(database, image_dir, tmp / "out.db", workers=1, seed=seed)
    except _Captured:
        pass
    finally:
        stage.judge_in_rounds = original
        shutil.rmtree(tmp, ignore_errors=True)
    return held


def gt_labels(db, matches, gt) -> dict[tuple[int, int], np.ndarray]:
    """pair -> bool (M,): the match lies within :data:`GT_THRESHOLD_PX` of its GT epipolar line."""
    from miho_bench.oracle import pair_distances

    names = {im.image_id: im.name for im in db.images()}
    kp = {i: db.keypoints(i) for i in names}
    return {(i, j): pair_distances(gt[names[i]], gt[names[j]], kp[i][m[:, 0]], kp[j][m[:, 1]]) <= GT_THRESHOLD_PX
            for (i, j), m in matches.items()}


def rotation_error(est, db, gt) -> float:
    """The largest angle (deg) between an estimated and a GT rotation after one global
    alignment of all of them."""
    from colmap_miho.geometry import project_to_so3, rotation_angle_deg
    from colmap_miho.reporting.keypoint_accuracy import camera_krt

    names = {im.image_id: im.name for im in db.images()}
    Rgt = {i: camera_krt(gt[names[i]])[1] for i in est.poses if names[i] in gt}
    if not Rgt:
        return float("nan")
    G = project_to_so3(sum(est.poses[i][0].T @ R for i, R in Rgt.items()))
    return max(rotation_angle_deg(est.poses[i][0] @ G, R) for i, R in Rgt.items())


def check(db, matches, labels, threads: int, hinges: bool, seed: int = 0):
    """The check's decision on ``matches``, the shares of correct / wrong matches it fails,
    its seconds, and the first estimate (recorded)."""
    from colmap_miho.sfm.global_estimate import GlobalEstimator
    from colmap_miho.verification import MatchCheckConfig, judge_in_rounds
    from colmap_miho.verification.hinge import find_hinges

    cfg = variant(MatchCheckConfig(mode="remove"), look_for_hinges=hinges)
    inner = GlobalEstimator(src=db, config=cfg, seed=seed, num_threads=threads)
    first: list = []

    class Recording:
        def estimate(self, m):
            est = inner.estimate(m)
            first.append(est)
            return est

        def place(self, *args, **kwargs):
            return inner.place(*args, **kwargs)

    t = time.perf_counter()
    d = judge_in_rounds(matches, Recording(), cfg)
    seconds = time.perf_counter() - t
    pairs = sorted(matches)
    ok = np.concatenate([labels[p] for p in pairs])
    failed = np.concatenate([d.failed.get(p, np.zeros(len(matches[p]), bool)) for p in pairs])
    mode = next(find_hinges(first[0].poses, first[0].pair_rotations, tolerance_deg=cfg.max_rotation_deg,
                            min_pairs=cfg.hinge_min_pairs, min_side_images=cfg.hinge_min_side_images),
                None) if first else None
    auc = coverage_auc(inner, first[0], matches, labels, cfg) if first and first[0].poses else float("nan")
    return d, float(failed[ok].mean()), float(failed[~ok].mean()) if (~ok).any() else 0.0, seconds, first, mode, auc


def coverage_auc(estimator, est, matches, labels, cfg) -> float:
    """ROC AUC of the arbiter's score (each pair's own coverage under the first estimate) for
    telling the GT-correct pairs (at least half their matches within the GT bound) from the
    GT-wrong ones, over every pair of two placed images that says something; 0.5: no better
    than chance."""
    from colmap_miho.verification.hinge import PairCoverage

    cov = PairCoverage(estimator, est, matches, cfg.max_threshold_px, cfg.min_pair_matches)
    scores = {p: cov(p) for p in matches if p[0] in est.poses and p[1] in est.poses}
    right = np.array([c for p, c in scores.items() if np.isfinite(c) and labels[p].mean() >= 0.5])
    wrong = np.array([c for p, c in scores.items() if np.isfinite(c) and labels[p].mean() < 0.5])
    if not len(right) or not len(wrong):
        return float("nan")
    above = (right[:, None] > wrong[None]).sum() + 0.5 * (right[:, None] == wrong[None]).sum()
    return float(above / (len(right) * len(wrong)))


def hinge_by_construction(db, matches, labels, cut: int, keep: int) -> dict:
    """``matches`` without all but the ``keep`` largest GT-correct pairs between the first
    ``cut`` images (in name order) and the others."""
    order = sorted(db.images(), key=lambda im: im.name)
    first = {im.image_id for im in order[:cut]}
    across = sorted((p for p in matches if (p[0] in first) != (p[1] in first) and labels[p].mean() >= 0.5),
                    key=lambda p: (-len(matches[p]), p))
    drop = set(across[keep:])
    return {p: m for p, m in matches.items() if p not in drop}


def run_one(scene: str, setting: str, features: int, seed: int, args) -> dict | None:
    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.reporting.gt_model import load_gt_poses

    inputs = scene_inputs(scene, args.data, args.cache)
    if inputs is None:
        logging.warning("skipped %s: not in %s", scene, args.data)
        return None
    image_dir, gt_dir = inputs
    n = MAX_FEATURES.get(scene, features)
    database = build_database(image_dir, args.cache / str(n) / scene, setting, n)
    matches = stage_input(database, image_dir, seed)
    gt = load_gt_poses(gt_dir)
    with tempfile.TemporaryDirectory(prefix="bench-hinge-db-") as tmp:
        shutil.copyfile(database, Path(tmp) / "db.db")  # the check only reads; opening migrates a copy
        with ColmapDatabase(Path(tmp) / "db.db") as db:
            labels = gt_labels(db, matches, gt)
            if args.hinge_by_construction:
                matches = hinge_by_construction(db, matches, labels, *args.hinge_by_construction)
                labels = {p: labels[p] for p in matches}
            d_on, correct_on, wrong_on, s_on, est_on, mode, auc = check(db, matches, labels, args.threads, True,
                                                                        args.check_seed)
            d_off, correct_off, wrong_off, s_off, *_ = check(db, matches, labels, args.threads, False, args.check_seed)
            names = {im.image_id: im.name for im in db.images()}
            err = rotation_error(est_on[0], db, gt) if est_on and est_on[0].poses else float("nan")
    found = [{"round": h.round, "angle_deg": round(h.hinge.angle_deg, 1), "verdict": h.verdict, "action": h.action,
              "images_a": sorted(names[i] for i in h.groups.side_a),
              "images_b": sorted(names[i] for i in h.groups.side_b),
              "mode_coverage": _median(h.mode_coverage), "estimate_coverage": _median(h.estimate_coverage),
              "pairs_unjudged": len(h.unjudged)} for h in d_on.hinges]
    hinge_seconds = sum(r.get("hinge", 0.0) for r in d_on.seconds)
    return {"scene": scene, "setting": setting, "features": n, "seed": seed, "pairs": len(matches),
            "matches": int(sum(len(m) for m in matches.values())),
            "gt_correct": int(sum(int(v.sum()) for v in labels.values())),
            "mode": None if mode is None else round(mode.angle_deg, 1), "hinges": found,
            "coverage_roc_auc": round(auc, 3),
            "correct_removed": round(100 * correct_on, 2), "correct_removed_off": round(100 * correct_off, 2),
            "wrong_removed": round(100 * wrong_on, 1), "wrong_removed_off": round(100 * wrong_off, 1),
            "identical": d_on.failed.keys() == d_off.failed.keys()
            and all(np.array_equal(d_on.failed[p], d_off.failed[p]) for p in d_on.failed),
            "max_rotation_error_deg": round(err, 1), "seconds": round(s_on, 1), "seconds_off": round(s_off, 1),
            "hinge_seconds": round(hinge_seconds, 2)}


def _median(scores: dict) -> float:
    values = [x for x in scores.values() if np.isfinite(x)]
    return round(float(np.median(values)), 3) if values else float("nan")


def table(rows: list[dict]) -> str:
    out = ["| scene | matching | SIFT | seed | pairs | estimate's worst image (deg) | coverage ROC AUC | "
           "hinge search | "
           "correct removed (without search) | wrong removed (without) | same verdicts | stage s (without) | "
           "search s |",
           "|---|---|---:|---:|---:|---:|---:|---|---|---|---|---|---:|"]
    for r in rows:
        if r["hinges"]:
            what = "; ".join(f"{h['angle_deg']} deg, {h['verdict']} ({h['mode_coverage']:.2f} against "
                             f"{h['estimate_coverage']:.2f}): {h['action']}" for h in r["hinges"])
        elif r["mode"] is not None:
            what = f"a {r['mode']} deg mode, not confirmed by 3D points"
        else:
            what = "silent"
        out.append(f"| {r['scene']} | {r['setting']} | {r['features']} | {r['seed']} | {r['pairs']} | "
                   f"{r['max_rotation_error_deg']} | {r['coverage_roc_auc']} | {what} | "
                   f"{r['correct_removed']:.2f}% ({r['correct_removed_off']:.2f}%) | "
                   f"{r['wrong_removed']:.1f}% ({r['wrong_removed_off']:.1f}%) | {'yes' if r['identical'] else 'no'} | "
                   f"{r['seconds']} ({r['seconds_off']}) | {r['hinge_seconds']} |")
    return "\n".join(out)


def database_arguments(ap: argparse.ArgumentParser) -> None:
    """The options that pick the databases (``--data``, ``--cache``, ``--scenes``, ``--settings``,
    ``--features``), shared with ``bench_match_check_estimate.py``."""
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "bench_hinge")
    ap.add_argument("--scenes", nargs="+", default=[*SHARED_SCENES, DEMO])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--features", nargs="+", type=int, default=[4096, 8192])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    database_arguments(ap)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0], help="refine seeds")
    ap.add_argument("--threads", type=int, default=2, help="global mapper threads (refine uses its worker count)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--hinge-by-construction", nargs=2, type=int, default=None, metavar=("CUT", "KEEP"))
    ap.add_argument("--check-seed", type=int, default=0,
                    help="the match check's seed (the mapper's and the track sample's)")
    ap.add_argument("--sample-every-component", action="store_true",
                    help="the estimate's track sample takes inconsistent components too (rebuilds a hinge)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.sample_every_component:
        from colmap_miho.sfm import global_estimate

        # the sample's consistency test sees no track holding two keypoints of one image
        global_estimate.repeated_image = lambda track, image, num_tracks: np.zeros(num_tracks, bool)
    rows = []
    for scene in args.scenes:
        for setting in args.settings:
            for features in ([MAX_FEATURES[scene]] if scene in MAX_FEATURES else args.features):
                for seed in args.seeds:
                    row = run_one(scene, setting, features, seed, args)
                    if row is not None:
                        rows.append(row)
                        print(table([row]).splitlines()[-1], flush=True)
    print()
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
