"""The terminal text of a quality report (:func:`format_report`) and its sections."""

from __future__ import annotations

import math


def _pct(x) -> str:
    return "  -  " if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:5.1f}"


def _px(x) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.3f}"


def auc_order(key: str) -> float:
    """Sort key of ``aucX`` keys: their threshold (keys of another kind last)."""
    value = auc_threshold_of(key)
    return float("inf") if value is None else value


def auc_threshold_of(key: str) -> float | None:
    """The threshold of an ``aucX`` key, or None for any other key."""
    if not key.startswith("auc"):
        return None
    try:
        return float(key[3:])
    except ValueError:
        return None


def format_keypoint_accuracy(ka: dict) -> list[str]:
    """Text lines of a ``keypoint_accuracy`` section (see :mod:`.keypoint_accuracy`)."""
    share = ka.get("epipolar_share_above")
    wrong = ka.get("wrong_track_share")
    return [
        f"keypoint accuracy under GT geometry ({ka['num_matches']} inlier matches, "
        f"{ka['num_tracks']} tracks seen by >= {ka['min_track_views']} GT images)",
        f"  epipolar distance median {_px(ka.get('epipolar_median_px'))} px, "
        f"{_pct(share).strip()}% above {ka['epipolar_threshold_px']:g} px",
        f"  GT track residual (tracks <= {ka['track_threshold_px']:g} px: {ka['num_measured_tracks']} tracks, "
        f"{ka['num_measured_observations']} observations): median {_px(ka.get('residual_median_px'))}, "
        f"mean {_px(ka.get('residual_mean_px'))}, p90 {_px(ka.get('residual_p90_px'))} px",
        f"  wrong tracks (> {ka['track_threshold_px']:g} px): {ka['num_wrong_tracks']} "
        f"({_pct(wrong).strip()}%); conflicting (two keypoints of one image): {ka['num_conflicting_tracks']}",
    ]


def format_report(report: dict) -> str:
    """A readable multi-line table of a report dict (AUCs in percent)."""
    lines = []
    r = report.get("reconstruction")
    if r:
        lines += [
            f"reconstruction  {r['num_reg_images']}/{r['num_images']} images registered, "
            f"{r['num_points3D']} points, {r['num_observations']} observations",
            f"                mean track length {r['mean_track_length']:.2f}, "
            + (f"mean observations per image {r['mean_observations_per_image']:.1f}, "
               if "mean_observations_per_image" in r else "")
            + f"mean reprojection error {r['mean_reprojection_error']:.3f} px",
        ]
    pc = report.get("pointcloud") or {}
    if pc.get("num_points"):
        lines.append(f"                sparse cloud: {100 * pc['outlier_share']:.1f}% statistical outliers, "
                     f"median spacing {pc['spacing_median']:.3g} model units")
    if any(k in report for k in ("model_pose_auc", "two_view_pose_auc_E", "two_view_pose_auc_F")):
        if lines:
            lines.append("")
        keys = [("model (all GT pairs)", "model_pose_auc"), ("two-view E (db matches)", "two_view_pose_auc_E"),
                ("two-view F (db, MAGSAC)", "two_view_pose_auc_F")]
        aucs = sorted({k for _, key in keys for k in report.get(key, {}) if auc_threshold_of(k) is not None},
                      key=auc_order)
        lines.append(f"{'pose AUC (%)':<26}" + "".join(f"{'@' + k[3:]:>7}" for k in aucs)
                     + f"{'mAA':>7}{'pairs':>7}{'failed':>7}")
        for label, key in keys:
            if key in report:
                a = report[key]
                lines.append(f"{label:<26}" + "".join(f"{_pct(a.get(k)):>7}" for k in aucs)
                             + f"{_pct(a['maa']):>7}{a['num_pairs']:>7}{a['num_failed']:>7}")
        ab = report.get("absolute", {})
        if ab.get("num_aligned", 0) >= 3:
            lines.append("")
            lines.append(
                f"after similarity alignment ({ab['num_aligned']} images): rotation error median "
                f"{ab['rotation_error_deg']['median']:.3f} deg (max {ab['rotation_error_deg']['max']:.3f}), "
                f"centre error median {ab['center_error']['median']:.4g} GT units "
                f"({100 * ab['center_error_rel']:.2f}% of the camera spread)"
            )
    if report.get("keypoint_accuracy"):
        lines.append("")
        lines += format_keypoint_accuracy(report["keypoint_accuracy"])
    return "\n".join(lines)
