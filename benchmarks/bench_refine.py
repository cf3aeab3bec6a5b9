"""Benchmark ``colmap-miho refine`` against pycolmap's own feature extraction + matching.

On a multi-view folder (default: ../shared/data/strecha_fountain_p11, 11 images, exhaustive
matching) this builds a COLMAP database in a temp folder with ``pycolmap.extract_features``
and ``pycolmap.match_exhaustive`` (CPU SIFT), then times ``refine_database`` on it (median of
``--repeats`` runs), and prints both figures and their ratio; with two or more repeats also the
first run's one-off start-up (imports, compiled-kernel loads, the worker pool's start) apart.
Optionally maps the input and the output with incremental mapping and prints registered
images, points and reprojection error (``--map``); ``--compare-verify`` adds a run with COLMAP re-verification.

Usage::

    python benchmarks/bench_refine.py [--scene DIR] [--workers N] [--repeats 3] [--map] [--compare-verify]
        [--recipe mop_miho_lsm] [--set key=value ...] [--max-features 8192] [--database PATH]
        [--matching default|permissive]

``--matching permissive`` matches with the permissive SIFT options of ``bench_accuracy.py``
(ratio 0.95, no cross-check) instead of COLMAP's defaults; the matching time is then that run's.

``--database PATH`` keeps the built database at PATH (with its extraction and matching times
in PATH.json) and reuses it on the next run with the same options, so that repeated timings
of ``refine`` skip the build; the ratio then uses the stored build times.

Timings taken while other processes use the cores are pessimistic.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def build_database(image_dir: Path, db: Path, max_features: int, matching: str = "default"
                   ) -> tuple[float, float]:
    import pycolmap
    from bench_accuracy import SETTINGS

    t = time.perf_counter()
    pycolmap.extract_features(
        str(db), str(image_dir), camera_mode=pycolmap.CameraMode.SINGLE,
        extraction_options={"max_image_size": 4096, "sift": {"max_num_features": max_features}},
        device=pycolmap.Device.cpu,
    )
    t_extract = time.perf_counter() - t
    t = time.perf_counter()
    options = pycolmap.FeatureMatchingOptions()
    for key, value in SETTINGS[matching].items():
        setattr(options.sift, key, value)
    pycolmap.match_exhaustive(str(db), matching_options=options, device=pycolmap.Device.cpu)
    return t_extract, time.perf_counter() - t


def _database(args: argparse.Namespace, image_dir: Path, tmp: Path) -> tuple[Path, float, float, bool]:
    """(database, extraction s, matching s, reused): built in ``tmp``, or kept at
    ``args.database`` (built there once, its times in a JSON file beside it)."""
    if args.database is None:
        db = tmp / "database.db"
        return (db, *build_database(image_dir, db, args.max_features, args.matching), False)
    meta_path = args.database.with_name(args.database.name + ".json")
    key = {"scene": str(args.scene.resolve()), "max_features": args.max_features}
    if args.matching != "default":  # keys of databases built before the option stay valid
        key["matching"] = args.matching
    if args.database.exists() and meta_path.exists():
        meta = json.loads(meta_path.read_text())
        if meta.get("key") == key:
            return args.database, meta["extract_s"], meta["match_s"], True
    args.database.unlink(missing_ok=True)
    args.database.parent.mkdir(parents=True, exist_ok=True)
    t_extract, t_match = build_database(image_dir, args.database, args.max_features, args.matching)
    meta_path.write_text(json.dumps({"key": key, "extract_s": t_extract, "match_s": t_match}))
    return args.database, t_extract, t_match, False


def map_database(db: Path, image_dir: Path) -> dict:
    import pycolmap

    out = Path(tempfile.mkdtemp(prefix="bench_map_"))
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = 0
    t = time.perf_counter()
    recs = pycolmap.incremental_mapping(str(db), str(image_dir), str(out), options=opts)
    secs = time.perf_counter() - t
    if not recs:
        return {"registered": 0, "seconds": secs}
    r = max(recs.values(), key=lambda r: r.num_reg_images())
    return {"registered": r.num_reg_images(), "points": r.num_points3D(),
            "track_length": round(r.compute_mean_track_length(), 2),
            "reproj_px": round(r.compute_mean_reprojection_error(), 3), "seconds": round(secs, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "strecha_fountain_p11")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--recipe", default=None)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--max-features", type=int, default=8192)
    parser.add_argument("--map", action="store_true", help="also map the input and the output(s)")
    parser.add_argument("--compare-verify", action="store_true",
                        help="also run with pipeline.verify=true (COLMAP re-verification)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--database", type=Path, default=None,
                        help="keep the built database here and reuse it when it exists")
    parser.add_argument("--matching", choices=("default", "permissive"), default="default",
                        help="COLMAP's default SIFT matching, or permissive (ratio 0.95, no cross-check)")
    args = parser.parse_args(argv)

    import pycolmap

    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.recipe import load_recipe

    pycolmap.logging.minloglevel = 2
    logging.basicConfig(level=logging.WARNING)
    image_dir = args.scene / "images"
    if not image_dir.is_dir():
        print(f"no image folder {image_dir}", file=sys.stderr)
        return 2
    n_images = len([p for p in image_dir.iterdir() if p.suffix.lower() in (".jpg", ".png", ".jpeg")])
    with tempfile.TemporaryDirectory(prefix="bench_refine_") as tmp:
        db, t_extract, t_match, reused = _database(args, image_dir, Path(tmp))
        print(f"scene {args.scene.name}: {n_images} images, cores {os.cpu_count()}")
        print(f"pycolmap extract_features {t_extract:.1f} s + match_exhaustive {t_match:.1f} s "
              f"= {t_extract + t_match:.1f} s (CPU SIFT, {args.max_features} features"
              f"{', stored times of the kept database' if reused else ''})")
        variants = [("default", [])]
        if args.compare_verify:
            variants.append(("verify", ["pipeline.verify=true"]))
        results = {}
        for name, extra in variants:
            recipe = load_recipe(args.recipe, [*args.overrides, *extra])
            times, summary = [], None
            for k in range(args.repeats if name == "default" else 1):
                out = Path(tmp) / f"out_{name}_{k}.db"
                t = time.perf_counter()
                summary = refine_database(db, image_dir, out, recipe=recipe, workers=args.workers,
                                          device=args.device, seed=0)
                times.append(time.perf_counter() - t)
            results[name] = (summary, times)
            med = statistics.median(times)
            print(f"refine [{recipe.name}{' ' + ' '.join(extra) if extra else ''}] median {med:.1f} s "
                  f"over {len(times)} run(s) {[round(x, 1) for x in times]}; stages "
                  + ", ".join(f"{k} {v:.1f}" for k, v in summary.seconds.items()))
            print(f"  pairs {summary.num_pairs} ({summary.pairs_filtered} filtered), matches "
                  f"{summary.matches_in} -> {summary.matches_kept}, keypoints moved "
                  f"{summary.keypoints_moved} (median {summary.median_displacement_px:.2f} px), "
                  f"workers {summary.workers}")
            if name == "default":
                print(f"ratio refine / (extract + match) = {med / (t_extract + t_match):.2f}")
                if len(times) >= 2:  # the one-off start-up, reported apart
                    later = statistics.median(times[1:])
                    print(f"  first run {times[0]:.1f} s (imports, kernel loads, worker start), later runs "
                          f"median {later:.1f} s: one-off start-up about {max(times[0] - later, 0.0):.1f} s; "
                          f"ratio without it {later / (t_extract + t_match):.2f}")
        if args.map:
            print("mapping input :", map_database(db, image_dir))
            for name, (summary, _) in results.items():
                print(f"mapping {name:7s}:", map_database(summary.output, image_dir))
    return 0


if __name__ == "__main__":
    sys.exit(main())
