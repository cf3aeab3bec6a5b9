"""Time ``colmap-miho import`` / ``export`` (hloc h5 <-> COLMAP database) on a synthetic scene.

    python benchmarks/bench_hloc_io.py [--images 30] [--points 3000] [--repeat 3]

Prints the median wall time of each step over ``--repeat`` runs, and per-image / per-pair
rates. The scene: pycolmap.synthesize_dataset, one camera, exhaustive pairs, 10 % outliers.
Timings taken while other jobs share the machine are pessimistic.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=30)
    ap.add_argument("--points", type=int, default=3000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import pycolmap

    from colmap_miho.adapters.exchange import export_hloc, import_hloc

    pycolmap.logging.minloglevel = 2
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        opts = pycolmap.SyntheticDatasetOptions(num_rigs=1, num_cameras_per_rig=1, num_frames_per_rig=args.images,
                                                num_points3D=args.points, inlier_match_ratio=0.9)
        pycolmap.set_random_seed(0)
        with pycolmap.Database.open(str(tmp / "src.db")) as db:
            pycolmap.synthesize_dataset(opts, db)
            (tmp / "images").mkdir()
            for im in db.read_all_images():
                cam = db.read_camera(im.camera_id)
                cv2.imwrite(str(tmp / "images" / im.name), np.zeros((cam.height, cam.width), np.uint8))
        export_hloc(tmp / "src.db", tmp / "f.h5", tmp / "m.h5", source="raw")

        times: dict[str, list[float]] = {"export (raw matches)": [], "import --no-verify": [], "import (verify)": []}
        stats = None
        for r in range(args.repeat):
            t = time.perf_counter()
            export_hloc(tmp / "src.db", tmp / f"f{r}.h5", tmp / f"m{r}.h5", source="raw")
            times["export (raw matches)"].append(time.perf_counter() - t)
            t = time.perf_counter()
            import_hloc(tmp / "f.h5", tmp / "m.h5", tmp / "images", tmp / f"nv{r}.db", verify=False)
            times["import --no-verify"].append(time.perf_counter() - t)
            t = time.perf_counter()
            stats = import_hloc(tmp / "f.h5", tmp / "m.h5", tmp / "images", tmp / f"v{r}.db", verify=True)
            times["import (verify)"].append(time.perf_counter() - t)
        print(f"scene: {stats.num_images} images, {stats.num_keypoints} keypoints, {stats.num_pairs} pairs, "
              f"{stats.num_matches} matches ({stats.num_inlier_matches} verified inliers)")
        for name, ts in times.items():
            med = statistics.median(ts)
            print(f"{name:24s} median {med:6.2f} s over {len(ts)} runs "
                  f"({1000 * med / stats.num_pairs:.2f} ms/pair, {1000 * med / stats.num_images:.1f} ms/image)")


if __name__ == "__main__":
    main()
