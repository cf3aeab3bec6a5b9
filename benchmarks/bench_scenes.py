"""Baseline vs colmap-miho SfM on the multi-view scenes of the shared data (GT poses).

For each scene: pycolmap SIFT + exhaustive matching (cached in WORK/<scene>/database.db),
then `compare` (map as is / refine + map, same seed), and one table row per side with
reconstruction statistics, model pose AUC against GT and the two-view E/F pose AUCs on the
dataset's pairs_with_gt.txt, plus wall times.

    python benchmarks/bench_scenes.py [--data ../shared/data] [--work /tmp/bench_scenes]
        [--scenes middlebury_temple_sparse_ring strecha_fountain_p11 strecha_entry_p10]
        [--recipe mop_miho_lsm] [--set pipeline.refine_keypoints=false] [--max-features 4096]
        [--repeats 3] [--camera-from-gt --refine-intrinsics none]

With ``--repeats N`` the mapping figures are medians of N runs (``compare --repeats``).
Known cameras in a leaner form, both matching settings and median of 3 runs:
``benchmarks/bench_known_cameras.py``.

Timings on a shared 2-core machine are pessimistic; the AUCs do not depend on them.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = ("middlebury_temple_sparse_ring", "strecha_fountain_p11", "strecha_entry_p10")


def pct(rep: dict, sec: str, key: str) -> str:
    """A percentage of ``rep[sec][key]``, the median over the runs when ``rep`` has repeats."""
    med = rep.get("repeats", {}).get("median", {})
    v = (med if sec in med else rep).get(sec, {}).get(key)
    return "-" if v is None else f"{100 * v:.1f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_scenes"))
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--recipe", default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=1, help="mapping runs per side (median reported)")
    ap.add_argument("--camera-from-gt", action="store_true", help="map with the GT intrinsics")
    ap.add_argument("--refine-intrinsics", default=None, choices=["all", "default", "none"])
    ap.add_argument("--tag", default="", help="suffix of the comparison folder (several recipes side by side)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    import pycolmap

    from colmap_miho.pipeline.jobs import JobOptions, compare_databases
    from colmap_miho.recipe import load_recipe
    from colmap_miho.sfm.extraction import extract_and_match

    pycolmap.logging.minloglevel = 1
    mapping = [f"mapping.refine_intrinsics={args.refine_intrinsics}"] if args.refine_intrinsics else []
    recipe = load_recipe(args.recipe, [*args.overrides, *mapping])
    rows = []
    for scene in args.scenes:
        root = args.data / scene
        if not (root / "images").is_dir():
            print(f"skip {scene}: no images at {root}", file=sys.stderr)
            continue
        work = args.work / scene
        db = work / "database.db"
        t0 = time.perf_counter()
        if not db.exists():
            extract_and_match(root / "images", db, max_features=args.max_features)
        t_feat = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = compare_databases(db, root / "images", work / f"compare{args.tag}", gt=root, recipe=recipe,
                                options=JobOptions(workers=args.workers, repeats=args.repeats,
                                                   gt_cameras=args.camera_from_gt))
        t_cmp = time.perf_counter() - t0
        for side in ("baseline", "refined"):
            rep = getattr(res, side)
            r = rep.get("reconstruction", {})
            rows.append({
                "scene": scene, "side": side, "reg": f"{r.get('num_reg_images', 0)}/{r.get('num_images', 0)}",
                "points": r.get("num_points3D", 0), "reproj": f"{r.get('mean_reprojection_error', 0):.3f}",
                "model": "/".join(pct(rep, "model_pose_auc", k) for k in ("auc5", "auc10", "auc20")),
                "E": "/".join(pct(rep, "two_view_pose_auc_E", k) for k in ("auc5", "auc10", "auc20")),
                "F": "/".join(pct(rep, "two_view_pose_auc_F", k) for k in ("auc5", "auc10", "auc20")),
                "map_s": f"{rep.get('mapping', {}).get('seconds', 0):.1f}",
                "refine_s": f"{res.refine.get('seconds', {}).get('total', 0):.1f}" if side == "refined" else "",
                "moved": res.refine.get("keypoints_moved", "") if side == "refined" else "",
            })
        print(f"{scene}: features {t_feat:.1f} s (0 = cached), compare {t_cmp:.1f} s -> {res.markdown}",
              file=sys.stderr)
    head = ["scene", "side", "reg", "points", "reproj", "model", "E", "F", "map_s", "refine_s", "moved"]
    print(f"recipe {recipe.name} {' '.join(args.overrides)}; AUC@5/10/20 in %; model = all GT pairs from the "
          f"reconstruction, E/F = two-view protocols on pairs_with_gt.txt")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in rows:
        print("| " + " | ".join(str(row[h]) for h in head) + " |")
    (args.work / f"bench_scenes{args.tag}.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
