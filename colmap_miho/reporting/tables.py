"""The side-by-side table of ``compare``: rows by group, cell formats, and whether a change is
better or worse. With repeated mapping runs a figure reads ``median [min-max]`` and overlapping
ranges are within the runs' spread."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..enums import StrEnum
from .keypoint_accuracy import EPIPOLAR_THRESHOLD_PX, TRACK_THRESHOLD_PX


class Better(StrEnum):
    """Which way a metric improves."""

    HIGHER = "higher"
    LOWER = "lower"
    NEITHER = "neither"  # a count whose change is no verdict by itself (points, observations)


class Verdict(StrEnum):
    """What a row's change means for colmap-miho's side."""

    BETTER = "better"
    WORSE = "worse"
    SAME = "same"  # equal as printed
    SPREAD = "within spread"  # repeated runs whose [min-max] ranges overlap
    NONE = ""  # a count (Better.NEITHER), or a value missing on one side


Row = tuple[str, tuple, str, Better]

_H, _L, _N = Better.HIGHER, Better.LOWER, Better.NEITHER
_STATS_ROWS: list[Row] = [
    ("registered images", ("reconstruction", "num_reg_images"), "d", _H),
    ("3D points", ("reconstruction", "num_points3D"), "d", _N),
    ("observations", ("reconstruction", "num_observations"), "d", _N),
    ("mean track length", ("reconstruction", "mean_track_length"), ".2f", _N),
    ("mean observations per image", ("reconstruction", "mean_observations_per_image"), ".1f", _N),
    ("mean reprojection error (px)", ("reconstruction", "mean_reprojection_error"), ".3f", _L),
    ("sparse-cloud outliers (%)", ("pointcloud", "outlier_share"), "%", _L),
]
_ABSOLUTE_ROWS: list[Row] = [
    ("rotation error median (deg)", ("absolute", "rotation_error_deg", "median"), ".3f", _L),
    ("centre error / camera spread (%)", ("absolute", "center_error_rel"), "%2", _L),
]
_KEYPOINT_ROWS: list[Row] = [
    # keypoint accuracy under GT geometry (colmap_miho.reporting.keypoint_accuracy)
    ("GT track residual median (px)", ("keypoint_accuracy", "residual_median_px"), ".3f", _L),
    ("GT track residual mean (px)", ("keypoint_accuracy", "residual_mean_px"), ".3f", _L),
    ("GT track residual p90 (px)", ("keypoint_accuracy", "residual_p90_px"), ".3f", _L),
    ("GT tracks measured", ("keypoint_accuracy", "num_measured_tracks"), "d", _N),
    (f"wrong tracks > {TRACK_THRESHOLD_PX:g} px (%)", ("keypoint_accuracy", "wrong_track_share"), "%", _L),
    ("conflicting tracks", ("keypoint_accuracy", "num_conflicting_tracks"), "d", _L),
    ("epipolar distance median (px)", ("keypoint_accuracy", "epipolar_median_px"), ".3f", _L),
    (f"epipolar distance > {EPIPOLAR_THRESHOLD_PX:g} px (%)", ("keypoint_accuracy", "epipolar_share_above"), "%",
     _L),
]
_AUC_SECTIONS = (("model pose", "model_pose_auc"), ("two-view E", "two_view_pose_auc_E"),
                 ("two-view F", "two_view_pose_auc_F"))
#: the table's groups, in order
GROUPS = ("reconstruction", "model pose", "two-view pose", "keypoints against GT")


def _auc_rows(section: str, label: str, reports: tuple[dict, ...]) -> list[Row]:
    from .report_text import auc_order, auc_threshold_of

    keys = sorted({k for rep in reports for k in (rep.get(section) or {}) if auc_threshold_of(k) is not None},
                  key=auc_order)
    rows: list[Row] = [(f"{label} AUC@{k[3:]} (%)", (section, k), "%", _H) for k in keys]
    if section == "model_pose_auc":
        rows.append(("model pose mAA (%)", (section, "maa"), "%", _H))
    return rows


def table_groups(baseline: dict, refined: dict) -> list[tuple[str, list[Row]]]:
    """(group, rows) for every group of :data:`GROUPS`, the AUC rows at the thresholds present."""
    reps = (baseline, refined)
    model, e, f = (_auc_rows(sec, label, reps) for label, sec in _AUC_SECTIONS)
    return list(zip(GROUPS, ([*_STATS_ROWS], [*model, *_ABSOLUTE_ROWS], [*e, *f], [*_KEYPOINT_ROWS]), strict=True))


def table_rows(baseline: dict, refined: dict) -> list[tuple[str, tuple, str]]:
    """(label, key path, format) of every table row, group by group."""
    return [(label, path, spec) for _, rows in table_groups(baseline, refined) for label, path, spec, _ in rows]


def _get(d: dict, path: tuple):
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def format_value(v, spec: str) -> str:
    """``v`` as a cell: ``"-"`` for None or non-finite; ``"%"``/``"%2"`` percent, ``"d"`` integer,
    else a :func:`format` spec."""
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
    rpt = rep.get("repeats")
    if rpt and _get(rpt.get("median", {}), path) is not None:
        med, lo, hi = (_get(rpt[k], path) for k in ("median", "min", "max"))
        text, low, high = (format_value(x, spec) for x in (med, lo, hi))
        return text if low == high else f"{text} [{low}-{high}]"
    v = _get(rep, path)
    return None if v is None else format_value(v, spec)


def _values(rep: dict, path: tuple) -> tuple[float, float, float] | None:
    """(value, low, high) of ``path`` (median, min, max with repeats); None when missing or not finite."""
    rpt = rep.get("repeats")
    if rpt and _get(rpt.get("median", {}), path) is not None:
        got = tuple(_get(rpt[k], path) for k in ("median", "min", "max"))
    else:
        v = _get(rep, path)
        got = (v, v, v)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in got):
        return None
    med, lo, hi = (float(v) for v in got)
    return med, lo, hi


def _change_text(before: float, after: float, spec: str) -> str:
    """The change as printed: percentage points for shares, else the difference and its relative size."""
    diff = after - before
    if spec in ("%", "%2"):
        return f"{100 * diff:+.{1 if spec == '%' else 2}f} pts"
    text = f"{diff:+.0f}" if spec == "d" else format(diff, "+" + spec)
    if not before:
        return text
    rel = 100 * diff / abs(before)
    return f"{text} ({rel:+.0f}%)" if abs(rel) >= 10 else f"{text} ({rel:+.1f}%)"


def _verdict(b, r, spec: str, better: Better) -> Verdict:
    if b is None or r is None:
        return Verdict.NONE
    if format_value(b[0], spec) == format_value(r[0], spec):
        return Verdict.SAME
    if better is Better.NEITHER:
        return Verdict.NONE
    if (b[1], b[2]) != (b[0], b[0]) and b[1] <= r[2] and r[1] <= b[2]:
        return Verdict.SPREAD
    return Verdict.BETTER if (r[0] > b[0]) == (better is Better.HIGHER) else Verdict.WORSE


@dataclass(frozen=True, kw_only=True)
class ComparedRow:
    """One row of the side-by-side table: the printed cells, the change and its verdict."""

    metric: str
    baseline: str
    refined: str
    change: str  # "-0.079 (-66%)", "+2.1 pts", "0" when the same, "-" when a side is missing
    verdict: Verdict
    better: Better


def comparison_groups(baseline: dict, refined: dict) -> list[tuple[str, list[ComparedRow]]]:
    """(group, rows) of every metric present in either report, with each change's verdict."""
    out = []
    for group, specs in table_groups(baseline, refined):
        rows = []
        for label, path, spec, better in specs:
            b, r = _cell(baseline, path, spec), _cell(refined, path, spec)
            if b is None and r is None:
                continue
            bv, rv = _values(baseline, path), _values(refined, path)
            verdict = _verdict(bv, rv, spec, better)
            if bv is None or rv is None:
                change = "-"
            else:
                change = "0" if verdict is Verdict.SAME else _change_text(bv[0], rv[0], spec)
            rows.append(ComparedRow(metric=label, baseline=b or "-", refined=r or "-", change=change,
                                    verdict=verdict, better=better))
        if rows:
            out.append((group, rows))
    return out


def comparison_rows(baseline: dict, refined: dict) -> list[tuple[str, str, str]]:
    """(metric, baseline, refined) text rows of :func:`comparison_groups`."""
    return [(row.metric, row.baseline, row.refined) for _, rows in comparison_groups(baseline, refined)
            for row in rows]


def verdict_summary(groups: list[tuple[str, list[ComparedRow]]]) -> str:
    """One line: how many rows are better, worse, the same; the worse ones named."""
    rows = [row for _, group in groups for row in group]
    count = {v: [r.metric for r in rows if r.verdict is v] for v in Verdict}
    better = len(count[Verdict.BETTER])
    parts = [f"better in {better} row{'' if better == 1 else 's'}",
             f"worse in {len(count[Verdict.WORSE])}" + (f" ({', '.join(count[Verdict.WORSE])})"
                                                        if count[Verdict.WORSE] else "")]
    if count[Verdict.SPREAD]:
        parts.append(f"within the runs' spread in {len(count[Verdict.SPREAD])}")
    parts.append(f"the same in {len(count[Verdict.SAME])}")
    return "colmap-miho against the baseline: " + ", ".join(parts) + "."


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
