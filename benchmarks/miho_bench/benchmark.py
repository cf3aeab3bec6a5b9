"""The paper's match-filtering benchmark on real pairs with ground truth.

For every front end (offline SIFT+NNR, corner-like GFTT, COLMAP's own matches), every dataset
and every GT pair it runs a list of *pipelines* - no filter, MAGSAC, MOP / MOP* / MOP+MiHo /
MOP+VSAC, each with pairwise NCC, NCC* or one-side ("track") refinement, and the peers
(AdaLAM, GMS when available, COLMAP's verification) - and measures per pair: precision and
recall averaged over 1..16 px, share filtered, pose AUC from F (with and without MAGSAC after the
filter) and from E, homography AUC for planar pairs, and seconds.

The module is pure evaluation logic on top of the public API; ``benchmarks/evaluate.py`` is the
command line that prints and writes the tables.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from colmap_miho.reporting.pose_metrics import auc_summary, pose_from_essential, pose_from_fundamental

from .datasets import PairGT, multiview_pairs, oxford_pairs
from .match_errors import gt_error
from .peers import adalam_mask, colmap_verification_mask, gms_available, gms_mask, magsac_mask
from .protocol import averaged_precision_recall, homography_auc, homography_error, homography_from_matches
from .variants import variant

log = logging.getLogger(__name__)

DATASETS = {
    "oxford": [f"oxford_affine/{s}" for s in ("graf", "boat", "bikes", "leuven")],
    "fountain": ["strecha_fountain_p11"],
    "entry": ["strecha_entry_p10"],
    "temple": ["middlebury_temple_sparse_ring"],
}

FILTERS = ("mop", "mop_star", "mop_miho", "mop_vsac")
REFINEMENTS = ("", "ncc", "ncc_star", "track")


def pipeline_names(quick: bool = False) -> list[str]:
    """Names of the evaluated pipelines: ``none``, ``magsac``, ``<filter>[+<refinement>]``, peers."""
    if quick:
        return ["none", "magsac", "mop", "mop_miho", "mop_miho+ncc", "mop_miho+track", "adalam", "colmap"]
    names = ["none", "magsac"]
    for f in FILTERS:
        names += [f if not r else f"{f}+{r}" for r in REFINEMENTS]
    names += ["adalam", "colmap"] + (["gms"] if gms_available() else [])
    return names


@dataclass
class PairInput:
    """One GT pair with its tentative matches from a front end."""

    pair: PairGT
    image1: np.ndarray
    image2: np.ndarray
    pts1: np.ndarray
    pts2: np.ndarray
    scores: np.ndarray
    affine1: np.ndarray | None = None
    affine2: np.ndarray | None = None


@dataclass
class PairOutcome:
    """Per-pair metrics of one pipeline."""

    precision: float
    recall: float
    filtered: float
    kept: int
    err_F: float
    err_F_magsac: float
    err_E: float
    err_H: float | None
    seconds: float
    extra: dict = field(default_factory=dict)


def load_pairs(data_root: Path, dataset: str, limit: int | None = None) -> list[PairGT]:
    """GT pairs of one dataset of ``DATASETS`` (the first ``limit`` per scene folder)."""
    pairs = []
    for folder in DATASETS[dataset]:
        scene = data_root / folder
        found = oxford_pairs(scene) if folder.startswith("oxford") else multiview_pairs(scene)
        pairs += found[:limit] if limit else found
    return pairs


def _filter_and_refine(name: str, inp: PairInput, seed: int):
    """Run one pipeline; return (kept mask (N,), refined pts1, pts2, seconds, extra)."""
    from colmap_miho.filtering.api import filter_matches
    from colmap_miho.refinement.config import NCCConfig
    from colmap_miho.refinement.pairwise import refine_pair

    n = len(inp.pts1)
    t0 = time.perf_counter()
    pts1, pts2 = inp.pts1, inp.pts2
    extra: dict = {}
    if name == "none":
        kept = np.ones(n, bool)
    elif name == "magsac":
        kept = magsac_mask(pts1, pts2, planar=inp.pair.is_planar, seed=seed)
    elif name == "adalam":
        kept = adalam_mask(pts1, pts2, inp.scores, inp.image1.shape, inp.image2.shape, inp.affine1, inp.affine2)
    elif name == "gms":
        kept = gms_mask(pts1, pts2, inp.image1.shape, inp.image2.shape)
    elif name == "colmap":
        kept = colmap_verification_mask(pts1, pts2, inp.image1.shape, inp.image2.shape, inp.pair.K1, inp.pair.K2)
    else:
        method, _, refinement = name.partition("+")
        result = filter_matches(pts1, pts2, method=method, seed=seed)
        kept = np.asarray(result.inliers, bool)
        extra["homographies"] = int(len(result.homographies))
        if refinement and kept.any():
            labels = np.asarray(result.labels)[kept]
            hom = np.asarray(result.patch_homographies)[labels]
            cfg = variant(NCCConfig.pairwise(), ellipse_mask=(refinement == "ncc_star"))
            move = "2" if refinement == "track" else "auto"
            ref = refine_pair(inp.image1, inp.image2, pts1[kept], pts2[kept], hom, move=move, config=cfg)
            pts1, pts2 = pts1.copy(), pts2.copy()
            pts1[kept], pts2[kept] = ref.pts1, ref.pts2
            extra["moved"] = int(np.sum(np.asarray(ref.moved_side) > 0))
    return kept, pts1, pts2, time.perf_counter() - t0, extra


def evaluate_pipeline(name: str, inp: PairInput, err_in: np.ndarray, seed: int = 0) -> tuple[PairOutcome, np.ndarray]:
    """Run pipeline ``name`` on one pair; return its metrics and the GT errors (pixels) of the
    matches it kept, after refinement."""
    kept, p1, p2, seconds, extra = _filter_and_refine(name, inp, seed)
    err_out = gt_error(inp.pair, p1, p2)
    precision, recall = averaged_precision_recall(err_in, kept, err_out)
    k1, k2 = p1[kept], p2[kept]
    err_F = err_FM = err_E = float("inf")
    err_H = None
    pair = inp.pair
    if pair.T_2from1 is not None:
        R, t = pair.T_2from1[:3, :3], pair.T_2from1[:3, 3]
        err_F = pose_from_fundamental(k1, k2, pair.K1, pair.K2, R, t, magsac=False, seed=seed).error_deg
        err_FM = pose_from_fundamental(k1, k2, pair.K1, pair.K2, R, t, magsac=True, seed=seed).error_deg
        err_E = pose_from_essential(k1, k2, pair.K1, pair.K2, R, t, seed=seed).error_deg
    if pair.H_2from1 is not None:
        err_H = homography_error(homography_from_matches(k1, k2), pair.H_2from1, inp.image1.shape, inp.image2.shape)
    n = len(kept)
    outcome = PairOutcome(precision, recall, 1.0 - kept.sum() / n if n else 0.0, int(kept.sum()),
                          err_F, err_FM, err_E, err_H, seconds, extra)
    return outcome, err_out[kept]


def summarize(outcomes: list[PairOutcome]) -> dict:
    """Dataset-level figures: mean P/R/filtered/seconds, AUCs over the pairs' errors."""
    if not outcomes:
        return {}
    mean = lambda k: float(np.nanmean([getattr(o, k) for o in outcomes]))  # noqa: E731
    out = {
        "pairs": len(outcomes),
        "precision": mean("precision"),
        "recall": mean("recall"),
        "filtered": mean("filtered"),
        "seconds": mean("seconds"),
    }
    if outcomes[0].err_H is not None:
        out["auc_H"] = homography_auc([o.err_H for o in outcomes])
    else:
        for key, attr in (("auc_F", "err_F"), ("auc_F_magsac", "err_F_magsac"), ("auc_E", "err_E")):
            s = auc_summary([getattr(o, attr) for o in outcomes])
            out[key] = {k: s[k] for k in ("auc5", "auc10", "auc20")}
    return out


def mean_auc(block: dict | None) -> float:
    """The tables' single figure: mean of the AUCs at the three thresholds."""
    return float(np.mean(list(block.values()))) if block else float("nan")


def markdown_table(frontend: str, results: dict[str, dict[str, dict]]) -> str:
    """One table per front end in the paper's layout: pipelines as rows, datasets as column
    groups. ``results[dataset][pipeline]`` is a :func:`summarize` dict."""
    datasets = list(results)
    pipelines = list(next(iter(results.values()))) if results else []
    head1 = "| pipeline |"
    head2 = "|---|"
    for d in datasets:
        planar = "auc_H" in next(iter(results[d].values()), {})
        cols = ["P", "R", "filt", "AUC^H"] if planar else ["P", "R", "filt", "AUC^F_M", "AUC^F", "AUC^E"]
        cols.append("s")
        head1 += "".join(f" {d} {c} |" for c in cols)
        head2 += "---|" * len(cols)
    lines = [f"### Front end: {frontend}", "", head1, head2]
    for p in pipelines:
        row = f"| {p} |"
        for d in datasets:
            s = results[d].get(p, {})
            if not s:
                row += " |" * (5 if "auc_H" in next(iter(results[d].values()), {}) else 7)
                continue
            row += f" {100 * s['precision']:.1f} | {100 * s['recall']:.1f} | {100 * s['filtered']:.1f} |"
            if "auc_H" in s:
                row += f" {100 * mean_auc(s['auc_H']):.1f} |"
            else:
                row += (f" {100 * mean_auc(s['auc_F_magsac']):.1f} | {100 * mean_auc(s['auc_F']):.1f} |"
                        f" {100 * mean_auc(s['auc_E']):.1f} |")
            row += f" {s['seconds']:.2f} |"
        lines.append(row)
    lines += ["", "P, R: precision and recall (%) averaged over 1..16 px; filt: share of matches removed (%);",
              "AUC: mean of the AUCs at 5/10/20 deg (pose; F_M = MAGSAC before the 8-point F) or 5/10/15 px",
              "(homography), in %; s: seconds per pair of the filter and refinement (not of the pose step).", ""]
    return "\n".join(lines)


def write_results(out_dir: Path, frontend: str, results: dict, errors: dict | None = None) -> tuple[Path, Path]:
    """Write ``<frontend>.md`` and ``<frontend>.json`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    md = out_dir / f"{frontend}.md"
    md.write_text(markdown_table(frontend, results))
    js = out_dir / f"{frontend}.json"
    js.write_text(json.dumps({"frontend": frontend, "results": results, "gt_errors": errors or {}},
                             indent=1, default=float))
    return md, js
