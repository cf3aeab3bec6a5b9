"""Figures of repeated mapping runs: per-run rows, median and range (min, max). Mapping varies from
run to run, so ``compare --repeats N`` treats each run as a sample; the database sections do not
depend on mapping and are evaluated once."""

from __future__ import annotations

import math

import numpy as np

#: report sections that change from one mapping run to the next
RUN_SECTIONS = ("reconstruction", "model_pose_auc", "absolute")
#: figures that are 0 when a run registered no model (the others are left out for that run)
FAILED_ZERO = {"reconstruction": ("num_reg_images", "num_points3D", "num_observations")}


def run_row(report: dict, seed: int, success: bool) -> dict:
    """One run's mapping figures ``{"seed", "success", section: {...}}``; a failed run has zeros."""
    row: dict = {"seed": int(seed), "success": bool(success)}
    for sec in RUN_SECTIONS:
        if isinstance(report.get(sec), dict) and report[sec]:
            row[sec] = report[sec]
    if not success:
        row["reconstruction"] = {k: 0 for k in FAILED_ZERO["reconstruction"]}
    return row


def _leaves(d: dict, prefix: tuple = ()) -> dict[tuple, float]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_leaves(v, prefix + (k,)))
        elif isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
            out[prefix + (k,)] = float(v)
    return out


def _put(d: dict, path: tuple, value) -> None:
    for k in path[:-1]:
        d = d.setdefault(k, {})
    d[path[-1]] = value


def summarise_runs(rows: list[dict]) -> dict:
    """``{"num_runs", "num_failed", "seeds", "runs", "median", "min", "max"}`` over the
    :func:`run_row` rows; a failed run's pose AUCs count as 0, non-finite values are ignored."""
    leaves = [_leaves({s: r[s] for s in RUN_SECTIONS if s in r}) for r in rows]
    auc_paths = {p for lv in leaves for p in lv
                 if p[0] == "model_pose_auc" and (p[1].startswith("auc") or p[1] == "maa")}
    for r, lv in zip(rows, leaves, strict=True):
        if not r["success"]:
            lv.update(dict.fromkeys(auc_paths, 0.0))
    paths = sorted({p for lv in leaves for p in lv}, key=str)
    out: dict = {"num_runs": len(rows), "num_failed": sum(not r["success"] for r in rows),
                 "seeds": [r["seed"] for r in rows], "runs": rows, "median": {}, "min": {}, "max": {}}
    for p in paths:
        vals = [lv[p] for lv in leaves if p in lv and math.isfinite(lv[p])]
        if not vals:
            continue
        _put(out["median"], p, float(np.median(vals)))
        _put(out["min"], p, float(min(vals)))
        _put(out["max"], p, float(max(vals)))
    return out
