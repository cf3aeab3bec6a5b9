"""The side-by-side table of ``compare``: which rows, and how a cell reads.

Rows are (label, key path into a report dict, format). The AUC rows follow the thresholds
present in the reports (``auc0.5`` ... ``auc20``). With repeated mapping runs (a ``repeats``
section, :mod:`colmap_miho.reporting.repeats`) a mapping figure reads ``median [min-max]``.
"""

from __future__ import annotations

import math

from .keypoint_accuracy import EPIPOLAR_THRESHOLD_PX, TRACK_THRESHOLD_PX

_STATS_ROWS = [
    ("registered images", ("reconstruction", "num_reg_images"), "d"),
    ("3D points", ("reconstruction", "num_points3D"), "d"),
    ("observations", ("reconstruction", "num_observations"), "d"),
    ("mean track length", ("reconstruction", "mean_track_length"), ".2f"),
    ("mean observations per image", ("reconstruction", "mean_observations_per_image"), ".1f"),
    ("mean reprojection error (px)", ("reconstruction", "mean_reprojection_error"), ".3f"),
]
_ABSOLUTE_ROWS = [
    ("rotation error median (deg)", ("absolute", "rotation_error_deg", "median"), ".3f"),
    ("centre error / camera spread (%)", ("absolute", "center_error_rel"), "%2"),
    ("sparse-cloud outliers (%)", ("pointcloud", "outlier_share"), "%"),
]
_KEYPOINT_ROWS = [
    # keypoint accuracy under GT geometry (colmap_miho.reporting.keypoint_accuracy)
    ("GT track residual median (px)", ("keypoint_accuracy", "residual_median_px"), ".3f"),
    ("GT track residual mean (px)", ("keypoint_accuracy", "residual_mean_px"), ".3f"),
    ("GT track residual p90 (px)", ("keypoint_accuracy", "residual_p90_px"), ".3f"),
    ("GT tracks measured", ("keypoint_accuracy", "num_measured_tracks"), "d"),
    (f"wrong tracks > {TRACK_THRESHOLD_PX:g} px (%)", ("keypoint_accuracy", "wrong_track_share"), "%"),
    ("conflicting tracks", ("keypoint_accuracy", "num_conflicting_tracks"), "d"),
    ("epipolar distance median (px)", ("keypoint_accuracy", "epipolar_median_px"), ".3f"),
    (f"epipolar distance > {EPIPOLAR_THRESHOLD_PX:g} px (%)", ("keypoint_accuracy", "epipolar_share_above"), "%"),
]
_AUC_SECTIONS = (("model pose", "model_pose_auc"), ("two-view E", "two_view_pose_auc_E"),
                 ("two-view F", "two_view_pose_auc_F"))


def _auc_rows(section: str, label: str, reports: tuple[dict, ...]) -> list[tuple]:
    from .report_text import auc_order, auc_threshold_of

    keys = sorted({k for rep in reports for k in (rep.get(section) or {}) if auc_threshold_of(k) is not None},
                  key=auc_order)
    rows = [(f"{label} AUC@{k[3:]} (%)", (section, k), "%") for k in keys]
    if section == "model_pose_auc":
        rows.append(("model pose mAA (%)", (section, "maa"), "%"))
    return rows


def table_rows(baseline: dict, refined: dict) -> list[tuple[str, tuple, str]]:
    """(label, key path, format) of every table row, the AUC rows at the thresholds present."""
    reps = (baseline, refined)
    model, e, f = (_auc_rows(sec, label, reps) for label, sec in _AUC_SECTIONS)
    return [*_STATS_ROWS, *model, *_ABSOLUTE_ROWS, *e, *f, *_KEYPOINT_ROWS]


def _get(d: dict, path: tuple):
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _fmt(v, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if spec == "%":
        return f"{100 * v:.1f}"
    if spec == "%2":
        return f"{100 * v:.2f}"
    if spec == "d" and isinstance(v, float) and not v.is_integer():
        return f"{v:.1f}"  # a median of an even number of runs
    return format(int(v) if spec == "d" else v, spec)


def _cell(rep: dict, path: tuple, spec: str) -> str | None:
    """The value of ``path``: plain, or with repeats the median and ``[min-max]``."""
    rpt = rep.get("repeats")
    if rpt and _get(rpt.get("median", {}), path) is not None:
        med, lo, hi = (_get(rpt[k], path) for k in ("median", "min", "max"))
        text = _fmt(med, spec)
        return text if _fmt(lo, spec) == _fmt(hi, spec) else f"{text} [{_fmt(lo, spec)}-{_fmt(hi, spec)}]"
    v = _get(rep, path)
    return None if v is None else _fmt(v, spec)


def comparison_rows(baseline: dict, refined: dict) -> list[tuple[str, str, str]]:
    """(metric, baseline, refined) text rows for every metric present in either report. With
    repeated runs (a ``repeats`` section) the mapping figures read ``median [min-max]``."""
    rows = []
    for label, path, spec in table_rows(baseline, refined):
        b, r = _cell(baseline, path, spec), _cell(refined, path, spec)
        if b is None and r is None:
            continue
        rows.append((label, b or "-", r or "-"))
    return rows


def comparison_markdown(baseline: dict, refined: dict, refine: dict, title: str = "colmap-miho comparison") -> str:
    """A markdown document: the side-by-side table plus the refine counters."""
    lines = [f"# {title}", "", "| metric | baseline | colmap-miho |", "|---|---:|---:|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in comparison_rows(baseline, refined)]
    runs = baseline.get("repeats", {}).get("num_runs")
    if runs:
        seeds = ", ".join(map(str, baseline["repeats"]["seeds"]))
        lines += ["", f"Mapping figures: median [min-max] of {runs} runs per side (seeds {seeds})."]
    if refine:
        lines += [
            "", f"Recipe `{refine.get('recipe', '')}`: {refine.get('pairs_filtered', 0)} pairs filtered, "
            f"{refine.get('matches_kept', 0)} of {refine.get('matches_in', 0)} matches kept, "
            f"{refine.get('keypoints_moved', 0)} keypoints moved (median "
            f"{refine.get('median_displacement_px', 0.0):.2f} px), "
            f"{refine.get('seconds', {}).get('total', float('nan')):.1f} s.",
        ]
    return "\n".join(lines) + "\n"
