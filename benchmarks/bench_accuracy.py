"""Keypoint accuracy before/after refinement, under GT geometry: the accuracy work's benchmark.

For the built-in demo scene (exact GT) and the multi-view scenes of the shared data, in both
COLMAP matching settings (``default``; ``permissive``: SIFT ratio 0.95, no cross-check), the
database is built once (pycolmap SIFT extraction + exhaustive matching + verification, cached
under ``--work``), then ``refine_database`` runs with each variant, and every database (the
input and each variant's output) is measured with
:func:`colmap_miho.reporting.keypoint_accuracy.keypoint_accuracy`: stored inlier matches'
distance to the GT epipolar lines, and residuals of their tracks triangulated with the GT
cameras (tracks seen by >= 3 GT images; tracks above 4 px are "wrong", counted apart).

    python benchmarks/bench_accuracy.py [--data ../shared/data] [--work /tmp/bench_accuracy]
        [--scenes demo strecha_castle_p19 middlebury_temple_sparse_ring strecha_fountain_p11
                  strecha_entry_p10]
        [--settings default permissive] [--recipe mop_miho_lsm] [--set ncc.template_radius=6]
        [--variant NAME[:key=value,key=value]] ... [--workers 2] [--seed 0] [--json out.json]

A variant is a name and ``--set`` overrides on top of ``--recipe`` and the global ``--set``s;
the special key ``recipe=NAME`` swaps the base recipe for that variant, e.g.::

    --variant filter_only:pipeline.refine_keypoints=false --variant ncc --variant r6:ncc.template_radius=6

Without ``--variant`` one variant runs: the recipe as given. The ``input`` row of each
scene/setting is the database before colmap-miho; "d_med %" is the change of the residual
median against it. With a variant that does not refine (``pipeline.refine_keypoints=false``, or the one
``--baseline`` names), every other variant's row also counts its *turned-wrong* matches (at most
4 px from the GT epipolar line in the baseline, more in the variant: same pair, same keypoint
indices; :mod:`colmap_miho.reporting.match_flips`), the turned-right ones and how far their
keypoints moved. Refinement statistics (``refine_stats``) are printed as extra columns,
whatever numeric keys they hold.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENES = ("strecha_castle_p19", "middlebury_temple_sparse_ring", "strecha_fountain_p11", "strecha_entry_p10")
DEMO = "demo"
SETTINGS = {
    # pycolmap's FeatureMatchingOptions().sift fields
    "default": {},
    "permissive": {"max_ratio": 0.95, "cross_check": False},
}
DEMO_IMAGES, DEMO_SIZE = 8, (640, 480)  # `colmap-miho demo` defaults
MAX_FEATURES = {DEMO: 2048}  # `colmap-miho demo` default; shared scenes: --max-features
# refine_stats keys that are not walk statistics (or are shown elsewhere)
SKIP_STATS = {"seconds", "workers"}


# --------------------------------------------------------------------------- inputs
def parse_variant(text: str) -> tuple[str, str | None, list[str]]:
    """``NAME[:key=value,key=value]`` -> (name, recipe or None, overrides)."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if not name or name == "input":
        raise ValueError(f"--variant needs a name other than 'input': {text!r}")
    recipe, overrides = None, []
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"--variant {name}: expected key=value, got {item!r}")
        if key.strip() == "recipe":
            recipe = value.strip()
        else:
            overrides.append(item)
    return name, recipe, overrides


def scene_databases(scenes, settings, data: Path, work: Path, max_features: int):
    """``(scene, setting, image folder, database)`` for every scene of ``scenes`` that has its data
    (the others are skipped, saying so) and every COLMAP matching setting, each database built once
    under ``work`` (:func:`build_database`)."""
    for scene in scenes:
        found = scene_inputs(scene, data, work)
        if found is None:
            print(f"skip {scene}: no images/ or gt_model/ under {data / scene}", file=sys.stderr)
            continue
        for setting in settings:
            yield scene, setting, found[0], build_database(found[0], work / scene, setting,
                                                           MAX_FEATURES.get(scene, max_features))


def scene_inputs(scene: str, data: Path, work: Path) -> tuple[Path, Path] | None:
    """(image folder, GT model folder) of a scene; the demo is rendered once into ``work``."""
    if scene == DEMO:
        from colmap_miho.reporting.demo_scene import make_demo_scene

        root = work / DEMO / "scene"
        images = root / "images"
        if not ((root / "gt_model" / "images.txt").is_file() and len(list(images.glob("*.png"))) == DEMO_IMAGES):
            make_demo_scene(root, num_images=DEMO_IMAGES, width=DEMO_SIZE[0], height=DEMO_SIZE[1], seed=0)
        return images, root / "gt_model"
    root = data / scene
    if not (root / "images").is_dir() or not (root / "gt_model").is_dir():
        return None
    return root / "images", root / "gt_model"


def build_database(image_dir: Path, folder: Path, setting: str, max_features: int) -> Path:
    """``folder/<setting>/database.db``: COLMAP SIFT features (cached in ``folder/features.db``)
    matched exhaustively with the setting's options and verified (pycolmap, CPU)."""
    import pycolmap

    from colmap_miho.sfm import colmap_log_to_file

    db = folder / setting / "database.db"
    if db.is_file():
        return db
    features = folder / "features.db"
    folder.mkdir(parents=True, exist_ok=True)
    with colmap_log_to_file(folder):
        if not features.is_file():
            # the options of colmap_miho.sfm.extraction.extract_and_match (single camera, SIMPLE_RADIAL)
            tmp = features.with_suffix(".tmp.db")
            tmp.unlink(missing_ok=True)
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = "SIMPLE_RADIAL"
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.sift.max_num_features = int(max_features)
            pycolmap.extract_features(str(tmp), str(image_dir), camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            tmp.rename(features)
        db.parent.mkdir(parents=True, exist_ok=True)
        tmp = db.with_suffix(".tmp.db")
        shutil.copyfile(features, tmp)
        matching = pycolmap.FeatureMatchingOptions()
        for key, value in SETTINGS[setting].items():
            setattr(matching.sift, key, value)
        pycolmap.match_exhaustive(str(tmp), matching_options=matching, device=pycolmap.Device.cpu)
        tmp.rename(db)
    return db


def measure(database: Path, gt_poses: dict) -> tuple[dict, object]:
    """The ``keypoint_accuracy`` dict of a database's verified inliers under the GT cameras, and
    the inliers (:class:`colmap_miho.reporting.report.DatabaseInliers`)."""
    from colmap_miho.reporting.report import database_keypoint_accuracy, read_database_inliers

    inliers = read_database_inliers(database)
    return database_keypoint_accuracy(inliers, gt_poses), inliers


def baseline_variant(variants: list[tuple[str, str | None, list[str]]], recipes: dict, name: str | None) -> str | None:
    """The variant the others' turned-wrong / turned-right matches are counted against: ``name``
    (``--baseline``), else the first variant that does not refine (``pipeline.refine_keypoints=false``),
    else None (not counted)."""
    if name is not None:
        if name not in recipes:
            raise SystemExit(f"--baseline {name}: no such --variant")
        return name
    return next((v for v, _, _ in variants if not recipes[v].pipeline.refine_keypoints), None)


def numeric_stats(stats: dict, prefix: str = "") -> dict:
    """Numeric leaves of ``refine_stats`` (nested dicts flattened with dots)."""
    out = {}
    for key, value in stats.items():
        if key in SKIP_STATS and not prefix:
            continue
        if isinstance(value, dict):
            out.update(numeric_stats(value, f"{prefix}{key}."))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[f"{prefix}{key}"] = value
    return out


# --------------------------------------------------------------------------- table
def _f(v, spec=".3f") -> str:
    if v is None or v == "":
        return "-"
    if isinstance(v, float):
        return format(v, spec) if v == v else "-"
    return str(v)


def table(rows: list[dict]) -> str:
    """Markdown table of the rows (fixed columns, then every refine_stats key seen)."""
    stat_keys = sorted({k for r in rows for k in r.get("refine_stats", {})})
    head = ["scene", "setting", "variant", "median", "mean", "p90", "d_med %", "wrong %", "epi med",
            "GT tracks", "kp moved", "turned wrong", "turned right", "wrong disp med", "wrong disp max",
            "refine s"] + stat_keys
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * 3 + "---:|" * (len(head) - 3)]
    for r in rows:
        k = r["keypoint_accuracy"]
        flips = r.get("epipolar_flips") or {}
        wrong = k.get("wrong_track_share")
        cells = [r["scene"], r["setting"], r["variant"], _f(k.get("residual_median_px")),
                 _f(k.get("residual_mean_px")), _f(k.get("residual_p90_px")), _f(r.get("median_change_pct"), "+.1f"),
                 _f(None if wrong is None else 100 * wrong, ".2f"), _f(k.get("epipolar_median_px")),
                 _f(k.get("num_measured_tracks")), _f(r.get("keypoints_moved")),
                 _f(flips.get("num_turned_wrong")), _f(flips.get("num_turned_right")),
                 _f(flips.get("wrong_disp_median_px"), ".1f"), _f(flips.get("wrong_disp_max_px"), ".1f"),
                 _f(r.get("refine_seconds"), ".1f")]
        cells += [_f(r.get("refine_stats", {}).get(s), ".3g") for s in stat_keys]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_accuracy"), help="cache of scenes and databases")
    ap.add_argument("--scenes", nargs="+", default=[DEMO, *SHARED_SCENES])
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--recipe", default=None, help="base recipe (default mop_miho_lsm)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override for every variant (repeatable)")
    ap.add_argument("--variant", dest="variants", action="append", default=[], metavar="NAME[:K=V,K=V]",
                    help="a variant to run (repeatable); 'recipe=NAME' swaps the base recipe")
    ap.add_argument("--baseline", default=None, metavar="NAME",
                    help="variant that the others' turned-wrong / turned-right matches (GT epipolar distance "
                         "<= 4 px in one, > 4 px in the other) are counted against; default: the first "
                         "variant with pipeline.refine_keypoints=false, if any")
    ap.add_argument("--workers", type=int, default=2, help="refine_database workers (default 2)")
    ap.add_argument("--seed", type=int, default=0,
                    help="refine_database seed (another seed shows the run-to-run spread)")
    ap.add_argument("--max-features", type=int, default=4096, help="SIFT features per image (demo: 2048)")
    ap.add_argument("--json", type=Path, default=None, help="write the rows as JSON")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    import pycolmap

    from colmap_miho.pipeline.refine_job import refine_database
    from colmap_miho.recipe import DEFAULT_RECIPE, load_recipe
    from colmap_miho.reporting.gt_model import load_gt_poses
    from colmap_miho.reporting.report import database_epipolar_flips

    pycolmap.logging.minloglevel = 1
    variants = [parse_variant(v) for v in args.variants] or [(args.recipe or "recipe", None, [])]
    if len({v[0] for v in variants}) != len(variants):
        raise SystemExit("--variant names must differ")
    recipes = {name: load_recipe(recipe or args.recipe, args.overrides + ov) for name, recipe, ov in variants}
    baseline = baseline_variant(variants, recipes, args.baseline)
    t_all = time.perf_counter()
    rows: list[dict] = []
    for scene in args.scenes:
        found = scene_inputs(scene, args.data, args.work)
        if found is None:
            print(f"skip {scene}: no images/ or gt_model/ under {args.data / scene}", file=sys.stderr)
            continue
        image_dir, gt_dir = found
        gt = load_gt_poses(gt_dir)
        for setting in args.settings:
            t0 = time.perf_counter()
            db = build_database(image_dir, args.work / scene, setting, MAX_FEATURES.get(scene, args.max_features))
            t_db = time.perf_counter() - t0
            base, _ = measure(db, gt)
            rows.append({"scene": scene, "setting": setting, "variant": "input", "keypoint_accuracy": base})
            inliers = {}
            for name, _, _ in variants:
                out = args.work / scene / setting / "variants" / f"{name}.db"
                out.parent.mkdir(parents=True, exist_ok=True)
                summary = refine_database(db, image_dir, out, recipe=recipes[name], overwrite=True, restart=True,
                                          workers=args.workers, seed=args.seed)
                k, inliers[name] = measure(summary.output, gt)
                b, a = base.get("residual_median_px"), k.get("residual_median_px")
                rows.append({
                    "scene": scene, "setting": setting, "variant": name, "keypoint_accuracy": k,
                    "median_change_pct": 100.0 * (a - b) / b if a is not None and b else None,
                    "keypoints_moved": summary.keypoints_moved,
                    "refine_seconds": summary.seconds.get("refine", 0.0),
                    "total_seconds": summary.seconds.get("total", 0.0),
                    "refine_stats": numeric_stats(summary.refine_stats),
                    "recipe": recipes[name].name, "overrides": args.overrides + [o for v in variants
                                                                                 if v[0] == name for o in v[2]],
                })
            if baseline is not None:
                for r in rows:
                    if r["scene"] == scene and r["setting"] == setting and r["variant"] in inliers \
                            and r["variant"] != baseline:
                        r["epipolar_flips"] = database_epipolar_flips(inliers[baseline], inliers[r["variant"]], gt)
            print(f"{scene}/{setting}: database {t_db:.1f} s (0 = cached), all done at "
                  f"{time.perf_counter() - t_all:.0f} s", file=sys.stderr)
    wall = time.perf_counter() - t_all
    print(f"base recipe {args.recipe or DEFAULT_RECIPE} {' '.join('--set ' + o for o in args.overrides)}; "
          f"residuals of stored-inlier tracks triangulated with the GT cameras (px, tracks <= 4 px), "
          f"d_med = change of the median vs input, wrong = tracks > 4 px, epi med = epipolar distance "
          f"median (px); turned wrong / right = matches <= 4 px from the GT epipolar line in "
          f"{baseline or '(no baseline)'} and > 4 px in the variant / the reverse, wrong disp = the "
          f"larger move of their two keypoints (px); {wall:.0f} s")
    print(table(rows))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"argv": sys.argv[1:] if argv is None else list(argv), "seconds": wall,
                                         "rows": rows}, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
