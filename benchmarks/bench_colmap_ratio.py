"""``refine``'s time as a share of COLMAP's own extraction + matching of the same images.

For each scene: pycolmap SIFT extraction (``--max-features``, 8192; single camera,
SIMPLE_RADIAL, CPU) and, per COLMAP matching setting, exhaustive matching and verification, each
timed, into ``--cache/<scene>/<setting>/database.db`` (the layout of ``bench_accuracy.py``'s
cache, so ``bench_known_cameras.py --cache`` maps them); then ``refine_database`` with the
default recipe twice on each database in this process: the first run (cold where the kernel
cache is cold) and the second (warm). Printed per database: verified matches, the seconds of
extraction, matching, both refine runs and the warm run's stages, and the warm ratio
``refine / (extraction + matching)``. A database already in the cache is rebuilt (the timings
are the point).

    python benchmarks/bench_colmap_ratio.py [--scenes strecha_castle_p19] [--settings default permissive]
        [--max-features 8192] [--cache /tmp/bench_accuracy_8k] [--workers 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import SETTINGS, scene_inputs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def extract(image_dir: Path, features: Path, max_features: int) -> float:
    """Seconds of COLMAP's SIFT extraction of ``image_dir`` into a new ``features`` database."""
    import pycolmap

    features.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = int(max_features)
    t0 = time.perf_counter()
    pycolmap.extract_features(str(features), str(image_dir), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=options, device=pycolmap.Device.cpu)
    return time.perf_counter() - t0


def match(features: Path, db: Path, setting: str) -> float:
    """Seconds of COLMAP's exhaustive matching and verification of a copy of ``features``."""
    import pycolmap

    db.parent.mkdir(parents=True, exist_ok=True)
    db.unlink(missing_ok=True)
    shutil.copyfile(features, db)
    options = pycolmap.FeatureMatchingOptions()
    for key, value in SETTINGS[setting].items():
        setattr(options.sift, key, value)
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(str(db), matching_options=options, device=pycolmap.Device.cpu)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_accuracy_8k"))
    ap.add_argument("--scenes", nargs="+", default=["strecha_castle_p19"])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--max-features", type=int, default=8192)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.sfm import colmap_log_to_file

    rows = []
    for scene in args.scenes:
        found = scene_inputs(scene, args.data, args.cache)
        if found is None:
            print(f"{scene}: no data, skipped")
            continue
        image_dir, _ = found
        folder = args.cache / scene
        folder.mkdir(parents=True, exist_ok=True)
        with colmap_log_to_file(folder):
            t_extract = extract(image_dir, folder / "features.db", args.max_features)
        for setting in args.settings:
            db = folder / setting / "database.db"
            with colmap_log_to_file(folder):
                t_match = match(folder / "features.db", db, setting)
            with ColmapDatabase(db) as d:
                verified = d.num_inlier_matches()
            runs = []
            for _ in range(2):
                out = folder / setting / "refined.db"
                t0 = time.perf_counter()
                s = refine_database(db, image_dir, out, overwrite=True, restart=True, workers=args.workers)
                runs.append({"seconds": time.perf_counter() - t0, "stages": s.seconds})
            colmap = t_extract + t_match
            row = {"scene": scene, "setting": setting, "max_features": args.max_features, "verified_matches": verified,
                   "extraction_s": round(t_extract, 1), "matching_s": round(t_match, 1),
                   "refine_first_s": round(runs[0]["seconds"], 1), "refine_warm_s": round(runs[1]["seconds"], 1),
                   "warm_stages_s": {k: round(v, 2) for k, v in runs[1]["stages"].items()},
                   "match_check_s": round(float((s.match_check or {}).get("seconds", 0.0)), 2),
                   "ratio_warm": round(runs[1]["seconds"] / colmap, 3)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
