"""Example: filter and refine a COLMAP database from Python, then map it.

Renders the small built-in demo scene (the one ``colmap-miho demo`` uses; needs the ``demo``
extra) and matches it with COLMAP's SIFT, unless a database and an image folder are given, runs
``colmap_miho.pipeline.refine_database`` (the input is never modified; the result is written
beside it as ``<stem>.miho.db``) and maps the result with pycolmap.

    python examples/refine_database.py [--database db.db --images imgs/] [--out DIR]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--database", type=Path)
    parser.add_argument("--images", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: a temp folder)")
    parser.add_argument("--no-refine", action="store_true")
    args = parser.parse_args(argv)

    import pycolmap

    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.recipe import load_recipe
    from colmap_miho.reporting.demo_scene import make_demo_scene
    from colmap_miho.sfm.extraction import extract_and_match

    work = args.out or Path(tempfile.mkdtemp(prefix="colmap_miho_example_"))
    if args.database is None:
        scene = make_demo_scene(work / "scene", num_images=4, width=480, height=360)
        database, images = work / "database.db", scene.image_dir
        extract_and_match(images, database, max_features=1024)
    else:
        database, images = args.database, args.images

    # None: the default recipe (mop_miho_lsm); "mop_miho_ncc" is the faster NCC-only one
    recipe = load_recipe(None, ["pipeline.refine_keypoints=false"] if args.no_refine else [])
    summary = refine_database(database, images, work / "refined.db", recipe=recipe, workers=1)
    print(summary.format())

    pycolmap.logging.minloglevel = 2
    (work / "sparse").mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(str(summary.output), str(images), str(work / "sparse"))
    best = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
    if best is None:
        print("mapping registered no image")
        return 1
    print(f"mapped: {best.num_reg_images()} images, {best.num_points3D()} points, "
          f"reprojection error {best.compute_mean_reprojection_error():.3f} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
