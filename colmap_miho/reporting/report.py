"""Quality report of a reconstruction and of a database's matches against ground truth:
:func:`build_report` returns a JSON-ready dict (model statistics, pose AUCs, absolute errors, the
paper's two-view protocols, keypoint accuracy, per-pair rows); AUCs are fractions."""

from __future__ import annotations

import logging
import math
from collections.abc import Hashable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..adapters.hloc import read_pairs_file
from ..errors import InvalidInput
from ..geometry import relative_pose
from . import pose_metrics as pm
from .gt_model import CameraPose
from .model_errors import absolute_errors, gt_pairs, model_pair_errors

log = logging.getLogger(__name__)


DEFAULT_AUC_THRESHOLDS_DEG: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
"""Pose-AUC thresholds of the reports (degrees): COLMAP's benchmark tolerances (0.5/1/5/10)
and the usual 2/20. 5/10/20 are always added (the ``auc5/auc10/auc20`` keys stay)."""


def auc_thresholds(thresholds=None) -> tuple[float, ...]:
    """``thresholds`` in degrees (None: the defaults) with 5/10/20 added, sorted, unique; raises
    ``ValueError`` for a non-positive or non-finite one."""
    given = DEFAULT_AUC_THRESHOLDS_DEG if thresholds is None else tuple(thresholds)
    for t in given:
        if not (isinstance(t, (int, float)) and math.isfinite(t) and t > 0):
            raise InvalidInput(f"AUC thresholds must be positive numbers of degrees, got {t!r}")
    return tuple(sorted({float(t) for t in (*given, *pm.AUC_THRESHOLDS_DEG)}))


def auc_key(threshold: float) -> str:
    """JSON key of the AUC at ``threshold`` degrees: ``auc0.5``, ``auc1``, ``auc20``."""
    t = float(threshold)
    return f"auc{int(t) if t.is_integer() else t}"


# --------------------------------------------------------------------------- reconstruction
def reconstruction_stats(rec) -> dict:
    """Statistics of a ``pycolmap.Reconstruction`` under ``Reconstruction.summary()``'s names."""
    n_pts = int(rec.num_points3D())
    n_reg = int(rec.num_reg_images())
    return {
        "num_cameras": int(rec.num_cameras()),
        "num_images": int(rec.num_images()),
        "num_reg_images": n_reg,
        "num_points3D": n_pts,
        "num_observations": int(rec.compute_num_observations()),
        "mean_track_length": float(rec.compute_mean_track_length()) if n_pts else 0.0,
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image()) if n_reg else 0.0,
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error()) if n_pts else 0.0,
    }


def pointcloud_figures(rec) -> dict:
    """Density / outlier figures of the sparse cloud; empty when they cannot be computed (logged)."""
    try:
        from . import pointcloud as pc

        xyz, _ = pc.reconstruction_points(rec)
        return pc.cloud_figures(xyz) if len(xyz) else {}
    except (ImportError, RuntimeError, ValueError) as exc:
        log.info("point-cloud figures skipped: %s", exc)
        return {}


# --------------------------------------------------------------------------- database matches
@dataclass(frozen=True, kw_only=True)
class DatabaseInliers:
    """A database's keypoints (name -> float64 ``(N, 2)``) and verified inliers ((name1, name2),
    name1 < name2 -> int64 ``(M, 2)`` indices)."""

    num_images: int
    keypoints: dict
    matches: dict

    def point_pairs(self, names: set[str] | None = None) -> dict:
        """``{(name1, name2): (pts1 (M, 2), pts2 (M, 2))}`` float64 pixels, name1 < name2."""
        return {(a, b): (self.keypoints[a][m[:, 0]], self.keypoints[b][m[:, 1]])
                for (a, b), m in self.matches.items()
                if names is None or (a in names and b in names)}


def read_database_inliers(database: str | Path) -> DatabaseInliers:
    """Keypoints and verified inlier matches of a database, read through a temporary copy."""
    from ..adapters.database import ColmapDatabase, validate_database
    from ..adapters.safety import check_database_path, read_copy
    from ..adapters.staged_write import private_tempdir

    database = check_database_path(database)
    kps: dict[str, np.ndarray] = {}
    matches: dict = {}
    with private_tempdir("colmap_miho_report_") as tmp:  # removed by the next run after a kill -9
        copy = Path(tmp) / "database.db"
        read_copy(database, copy)  # refuses a database in use or with a hot journal
        validate_database(copy, name=database)
        with ColmapDatabase(copy) as db:
            images = {r.image_id: r.name for r in db.images()}
            for pair in db.pairs("verified"):
                i, j = pair.image_id1, pair.image_id2
                ni, nj = images.get(i), images.get(j)
                if ni is None or nj is None:
                    continue
                for k, n in ((i, ni), (j, nj)):
                    if n not in kps:
                        kps[n] = db.keypoints(k)
                m = db.matches(i, j, "verified").astype(np.int64)
                matches[(ni, nj) if ni < nj else (nj, ni)] = m if ni < nj else m[:, ::-1].copy()
    return DatabaseInliers(num_images=len(images), keypoints=kps, matches=matches)


def read_database_matches(database: str | Path, names: set[str] | None = None) -> tuple[int, dict]:
    """``(num_images, {(name1, name2): (pts1 (M, 2), pts2 (M, 2))})``: verified inliers as float64
    pixel pairs, name1 < name2, optionally only pairs within ``names``; read through a copy."""
    inl = read_database_inliers(database)
    return inl.num_images, inl.point_pairs(names)


def database_keypoint_accuracy(inliers: DatabaseInliers, gt: dict[str, CameraPose], **thresholds) -> dict:
    """The ``keypoint_accuracy`` section: a database's inliers under the GT cameras."""
    from .keypoint_accuracy import keypoint_accuracy

    if not set(inliers.keypoints) & set(gt):
        log.warning("no database image is in the GT (names differ?): keypoint accuracy is empty")
    cameras: dict[Hashable, object] = {name: pose for name, pose in gt.items()}
    return keypoint_accuracy(cameras, inliers.keypoints, inliers.matches, **thresholds).to_dict()


def database_epipolar_flips(before: DatabaseInliers, after: DatabaseInliers, gt: dict[str, CameraPose],
                            **thresholds) -> dict:
    """Epipolar flips between two databases of one scene under the GT cameras, as a JSON-ready dict."""
    from .match_flips import epipolar_flips

    cameras: dict[Hashable, object] = {name: pose for name, pose in gt.items()}
    return epipolar_flips(cameras, before.keypoints, after.keypoints, before.matches, after.matches,
                          **thresholds).to_dict()


def two_view_pair_errors(
    matches: dict, gt: dict[str, CameraPose], pairs: list[tuple[str, str]], *, seed: int = 0,
    protocols: tuple[str, ...] = ("E", "F"), magsac_for_f: bool = True,
) -> dict[tuple[str, str], dict]:
    """The paper's two-view pose protocols ("E", "F") on every pair: ``{pair: {"num_matches", "E",
    "F"}}`` (errors in degrees; a pair without matches fails with ``inf``)."""
    out = {}
    for a, b in pairs:
        key = (a, b) if a < b else (b, a)
        a, b = key
        row: dict = {"num_matches": 0}
        for p in protocols:
            row[p] = math.inf
        if key in matches and a in gt and b in gt:
            p1, p2 = matches[key]
            row["num_matches"] = int(len(p1))
            R_gt, t_gt = relative_pose((gt[a].R, gt[a].t), (gt[b].R, gt[b].t))
            if "E" in protocols:
                row["E"] = pm.pose_from_essential(p1, p2, gt[a].K, gt[b].K, R_gt, t_gt, seed=seed).error_deg
            if "F" in protocols:
                row["F"] = pm.pose_from_fundamental(
                    p1, p2, gt[a].K, gt[b].K, R_gt, t_gt, magsac=magsac_for_f, seed=seed
                ).error_deg
        out[key] = row
    return out


def default_eval_pairs(gt_path: str | Path | None, gt: dict[str, CameraPose]) -> tuple[list[tuple[str, str]], str]:
    """``(pairs, description)``: the dataset's ``pairs_with_gt.txt`` when it has one, else all GT pairs."""
    if gt_path is not None:
        from .gt_model import resolve_model_dir

        model_dir = resolve_model_dir(gt_path)
        for cand in (model_dir.parent / "pairs_with_gt.txt", Path(gt_path) / "pairs_with_gt.txt"):
            if cand.is_file():
                pairs = [p for p in read_pairs_file(cand) if p[0] in gt and p[1] in gt]
                if pairs:
                    return pairs, str(cand)
    return gt_pairs(gt), "all GT pairs"


# --------------------------------------------------------------------------- the report
def _errors_for(rows: dict, key: str) -> list[float]:
    return [r[key] for r in rows.values()]


def build_report(
    model: str | Path | None = None,
    *,
    reconstruction=None,
    database: str | Path | None = None,
    gt: str | Path | None = None,
    pairs: list[tuple[str, str]] | str | Path | None = None,
    seed: int = 0,
    thresholds=None,
) -> dict:
    """Evaluate a model and/or a database's matches against ``gt`` and return the report dict.

    ``model`` (a folder) or ``reconstruction``; without either, only ``database`` is evaluated.
    ``pairs``: name pairs or a pairs file for the two-view AUCs. ``thresholds``: pose-AUC thresholds
    in degrees (5/10/20 always added)."""
    from ..arguments import check_paths, check_seed
    from .gt_model import load_gt_poses, load_reconstruction, poses_from_reconstruction

    check_paths(model=model, database=database, gt=gt, optional=("model", "database", "gt"))
    check_seed(seed)
    if reconstruction is None and model is None and (database is None or gt is None):
        raise InvalidInput("give model or reconstruction, or database and gt")
    thresholds = auc_thresholds(thresholds)
    rec = reconstruction
    if rec is None and model is not None:
        rec = load_reconstruction(model)
    report: dict = {"model": str(model) if model is not None else None}
    if rec is not None:
        report["reconstruction"] = reconstruction_stats(rec)
        report["pointcloud"] = pointcloud_figures(rec)
    inliers = db_matches = None
    if database is not None:
        inliers = read_database_inliers(database)
        db_matches = inliers.point_pairs()
        if rec is not None:
            # a written model holds only its own images: count the database's for num_images
            report["reconstruction"]["num_images"] = max(report["reconstruction"]["num_images"],
                                                         inliers.num_images)
    if gt is None:
        if database is not None:
            log.warning("--database given without --gt: two-view pose AUCs need ground truth; skipped")
        return report
    gt_poses = load_gt_poses(gt)
    rows: dict = {}
    if rec is not None:
        est = poses_from_reconstruction(rec)
        report["gt"] = {"path": str(gt), "num_images": len(gt_poses),
                        "num_registered": len(set(est) & set(gt_poses))}
        missing = sorted(set(est) - set(gt_poses))
        if missing:
            log.warning("%d registered images are not in the GT (names differ?), e.g. %s", len(missing), missing[0])
        all_pairs = gt_pairs(gt_poses)
        model_err = model_pair_errors(est, gt_poses, all_pairs)
        report["model_pose_auc"] = pm.auc_summary(list(model_err.values()), thresholds)
        report["absolute"] = absolute_errors(est, gt_poses)
        rows = {k: {"model": v} for k, v in model_err.items()}
    else:
        model_err = {}
        report["gt"] = {"path": str(gt), "num_images": len(gt_poses)}
    if inliers is not None and db_matches is not None:  # a database was given
        if pairs is None:
            eval_pairs, src = default_eval_pairs(gt, gt_poses)
        elif isinstance(pairs, (str, Path)):
            eval_pairs, src = read_pairs_file(pairs), str(pairs)
        else:
            eval_pairs, src = list(pairs), "given pairs"
        tv = two_view_pair_errors(db_matches, gt_poses, eval_pairs, seed=seed)
        for proto in ("E", "F"):
            s = pm.auc_summary(_errors_for(tv, proto), thresholds)
            s["pairs"] = src
            report[f"two_view_pose_auc_{proto}"] = s
        for k, r in tv.items():
            if rec is not None:
                rows.setdefault(k, {"model": model_err.get(k, math.inf)}).update(r)
            else:
                rows.setdefault(k, {}).update(r)
        report["database"] = str(database)
        report["keypoint_accuracy"] = database_keypoint_accuracy(inliers, gt_poses)
    report["pairs"] = [
        {"name1": a, "name2": b, **{k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in r.items()}}
        for (a, b), r in sorted(rows.items())
    ]
    return report


def json_safe(obj):
    """Copy of ``obj`` with NaN/inf floats as None and paths/tuples as JSON types."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_report_json(report: dict, path: str | Path) -> Path:
    """Write ``report`` as indented JSON (NaN/inf as null), whole or not at all; returns the path."""
    import json

    from ..adapters.staged_write import write_text_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(json_safe(report), indent=2))
    return path
