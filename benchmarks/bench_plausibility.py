"""Does the read check tell an image file from another one of the same size?

For each scene (the databases ``bench_accuracy.py`` builds, cached under ``--work``) the share of
sampled keypoints that stand out from their surroundings (:mod:`colmap_miho.pipeline.plausibility`)
is measured on each image's own file and on the next image's file (a shuffled folder), with the
keypoints' SIFT scale and without it (keypoints imported without a shape); the table gives the
range over the images and how many the check flags.

    python benchmarks/bench_plausibility.py [--scenes demo strecha_castle_p19 ...] [--work /tmp/bench_accuracy]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import DEMO, MAX_FEATURES, SHARED_SCENES, build_database, scene_inputs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.adapters.images import read_gray_float
    from colmap_miho.pipeline.plausibility import implausible, keypoint_support

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_accuracy"))
    ap.add_argument("--scenes", nargs="+", default=[DEMO, *SHARED_SCENES])
    ap.add_argument("--max-features", type=int, default=4096)
    args = ap.parse_args()
    print("| scene | keypoints | own file: share (min-max) | flagged | next file: share (min-max) | flagged |")
    print("|---|---|---|---|---|---|")
    for scene in args.scenes:
        inputs = scene_inputs(scene, args.data, args.work)
        if inputs is None:
            print(f"| {scene} | (absent) | | | | |")
            continue
        image_dir, _ = inputs
        db_path = build_database(image_dir, args.work / scene, "default", MAX_FEATURES.get(scene, args.max_features))
        with ColmapDatabase(db_path) as db:
            names = {im.image_id: im.name for im in db.images()}
            ids = sorted(names)
            xy = {i: db.keypoints(i) for i in ids}
            affine = {i: db.keypoint_affines(i) for i in ids}
        images = {i: read_gray_float(image_dir / names[i]) for i in ids}
        for shaped in (True, False):
            scale = {i: np.sqrt(np.abs(np.linalg.det(affine[i]))) if shaped and affine[i] is not None else None
                     for i in ids}
            own = [keypoint_support(images[i], xy[i], scale[i], seed=i) for i in ids]
            nxt = [keypoint_support(images[ids[(k + 1) % len(ids)]], xy[i], scale[i], seed=i)
                   for k, i in enumerate(ids)]
            shares = [s for s, _ in own], [s for s, _ in nxt]
            print(f"| {scene} | {'SIFT scale' if shaped else 'no shape'} | {min(shares[0]):.2f}-{max(shares[0]):.2f} "
                  f"| {sum(implausible(*r) for r in own)} of {len(ids)} | {min(shares[1]):.2f}-{max(shares[1]):.2f} "
                  f"| {sum(implausible(*r) for r in nxt)} of {len(ids)} |")


if __name__ == "__main__":
    main()
