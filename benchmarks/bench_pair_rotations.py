"""Each pair's own rotation (the match check's trust evidence): posed from the stored model against
a new RANSAC, judged by the ground truth, with their time.

For each Strecha scene and COLMAP matching setting, the database of ``bench_accuracy.py``
(cached under ``--work``) and a copy of it verified again with the GT intrinsics as focal
priors (so that COLMAP stores an essential matrix, config CALIBRATED, where it prefers one). On
every verified pair's inliers (evenly spaced, at most 512, as the check takes them) with the GT
cameras, it prints how long the RANSAC estimate (``estimate_two_view_geometry``) and posing the
stored model (``estimate_two_view_geometry_pose``) take, how often the two disagree by more
than 5 deg, which is nearer the GT then, and each one's GT rotation error (median, pairs over
5 deg). ``--models`` picks the stored models posed: ``calibrated`` (what the check does: an E
only, RANSAC for the rest) or ``all`` (every stored F or H too)::

    python benchmarks/bench_pair_rotations.py --work W [--models calibrated|all] [--json F]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import SETTINGS, scene_databases  # noqa: E402

STRECHA = ("strecha_castle_p19", "strecha_entry_p10", "strecha_fountain_p11")
REPO = Path(__file__).resolve().parents[1]


def gt_cameras(db, gt) -> dict:
    """image id -> a PINHOLE ``pycolmap.Camera`` of the GT intrinsics at the database's image size,
    with a focal prior."""
    import pycolmap

    cams = {}
    for im in db.images():
        g = gt[im.name]
        sx, sy = im.width / g.width, im.height / g.height
        cam = pycolmap.Camera(model="PINHOLE", width=im.width, height=im.height,
                              params=[g.K[0, 0] * sx, g.K[1, 1] * sy, (g.K[0, 2] + 0.5) * sx, (g.K[1, 2] + 0.5) * sy])
        cam.has_prior_focal_length = True
        cams[im.image_id] = cam
    return cams


def verified_with_gt_priors(src: Path, dst: Path, gt) -> Path:
    """A copy of ``src`` whose cameras carry the GT intrinsics as focal priors, verified again."""
    import pycolmap

    if dst.exists():
        return dst
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_suffix(".tmp.db")
    shutil.copy(src, tmp)
    with pycolmap.Database.open(str(tmp)) as db:
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        for im in db.read_all_images():
            g, c = gt[im.name], cams[im.camera_id]
            sx, sy = c.width / g.width, c.height / g.height
            cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=c.width, height=c.height, camera_id=c.camera_id,
                                  params=[0.5 * (g.K[0, 0] * sx + g.K[1, 1] * sy), (g.K[0, 2] + 0.5) * sx,
                                          (g.K[1, 2] + 0.5) * sy, 0.0])
            cam.has_prior_focal_length = True
            db.update_camera(cam)
        db.clear_two_view_geometries()
    opts = pycolmap.TwoViewGeometryOptions()
    opts.ransac.random_seed = 0
    pycolmap.geometric_verification(str(tmp), two_view_geometry_options=opts)
    tmp.rename(dst)
    return dst


def compare(path: Path, gt, models: str) -> dict:
    """The two ways on every verified pair of the database at ``path``."""
    import pycolmap

    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.geometry import rotation_angle_deg, spread_rows
    from colmap_miho.sfm.global_estimate import _pair_rotations

    with ColmapDatabase(path) as db:
        kp = {im.image_id: db.raw_keypoints(im.image_id)[:, :2].astype(np.float64) for im in db.images()}
        name = {im.image_id: im.name for im in db.images()}
        cams = gt_cameras(db, gt)
        matches, stored = {}, {}
        for rec in db.pairs("verified"):
            pair = (rec.image_id1, rec.image_id2)
            tvg = db.verified_model(*pair)
            if tvg is None or len(tvg.inlier_matches) < 15:
                continue
            m = np.asarray(tvg.inlier_matches, np.int64)
            matches[pair] = m[spread_rows(len(m), 512)]
            stored[pair] = tvg
    configs = Counter(pycolmap.TwoViewGeometryConfiguration(int(t.config)).name for t in stored.values())
    t0 = time.perf_counter()
    ransac = _pair_rotations(pycolmap, matches, {}, kp, cams, 0, 1)
    t_ransac = time.perf_counter() - t0
    t0 = time.perf_counter()
    posed = _pair_rotations(pycolmap, matches, stored, kp, cams, 0, 1) if models == "calibrated" else \
        _every_model_posed(pycolmap, matches, stored, kp, cams, ransac)
    t_posed = time.perf_counter() - t0

    def err(R, p):
        gi, gj = gt[name[p[0]]], gt[name[p[1]]]
        return rotation_angle_deg(R, gj.R @ gi.R.T)

    both = [p for p in ransac if p in posed]
    apart = [p for p in both if rotation_angle_deg(ransac[p], posed[p]) > 5.0]
    e_r = np.array([err(ransac[p], p) for p in both])
    e_p = np.array([err(posed[p], p) for p in both])
    return {"pairs": len(matches), "configs": dict(configs),
            "ransac_s": round(t_ransac, 3), "posed_s": round(t_posed, 3),
            "apart_5deg": len(apart), "apart_ransac_nearer": sum(err(ransac[p], p) < err(posed[p], p) for p in apart),
            "apart_posed_nearer": sum(err(posed[p], p) < err(ransac[p], p) for p in apart),
            "gt_error_median_deg": [round(float(np.median(e_r)), 3), round(float(np.median(e_p)), 3)],
            "gt_over_5deg": [int((e_r > 5).sum()), int((e_p > 5).sum())]}


def _every_model_posed(pc, matches, stored, kp, cams, ransac) -> dict:
    """Every stored model (E, F or H) posed over the pair's matches; the RANSAC rotation where
    posing fails."""
    out = {}
    for (i, j), m in matches.items():
        tvg = stored[(i, j)]
        tvg.inlier_matches = np.ascontiguousarray(m, np.uint32)
        try:
            ok = pc.estimate_two_view_geometry_pose(cams[i], kp[i], cams[j], kp[j], tvg)
        except ValueError:
            ok = False
        if ok:
            out[(i, j)] = np.asarray(tvg.cam2_from_cam1.rotation.matrix(), np.float64)
        elif (i, j) in ransac:
            out[(i, j)] = ransac[(i, j)]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, required=True, help="cache of the databases")
    ap.add_argument("--scenes", nargs="+", default=list(STRECHA))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--models", choices=("calibrated", "all"), default="calibrated")
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import pycolmap

    from colmap_miho.reporting.gt_model import strecha_poses

    pycolmap.logging.minloglevel = 2
    rows = []
    print("database | pairs | configs | RANSAC s | posed s | apart > 5 deg (RANSAC / posed nearer the GT) | "
          "GT error median RANSAC / posed (deg) | pairs > 5 deg from the GT RANSAC / posed")
    for scene, setting, image_dir, db in scene_databases(args.scenes, args.settings, args.data, args.work,
                                                         args.max_features):
        gt = strecha_poses(args.data / scene / "gt_full_res", image_dir)
        priors = verified_with_gt_priors(db, args.work / "gt_priors" / scene / setting / "database.db", gt)
        for label, path in (("as built", db), ("GT focal priors", priors)):
            r = {"scene": scene, "setting": setting, "database": label, **compare(path, gt, args.models)}
            rows.append(r)
            print(f"{scene}/{setting} ({label}) | {r['pairs']} | {r['configs']} | "
                  f"{r['ransac_s']} | {r['posed_s']} | "
                  f"{r['apart_5deg']} ({r['apart_ransac_nearer']} / {r['apart_posed_nearer']}) | "
                  f"{r['gt_error_median_deg'][0]} / {r['gt_error_median_deg'][1]} | "
                  f"{r['gt_over_5deg'][0]} / {r['gt_over_5deg'][1]}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"argv": sys.argv[1:] if argv is None else argv, "models": args.models,
                                         "rows": rows}, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
