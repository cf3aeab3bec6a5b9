"""Run the match-filtering benchmark and write its tables, JSON and plots.

``benchmarks/evaluate.py`` is the command line; :func:`run_benchmark` is what a test calls in
quick mode.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from .benchmark import DATASETS, evaluate_pipeline, load_pairs, mean_auc, pipeline_names, summarize, write_results
from .frontend_cache import load_inputs
from .match_errors import gt_error

log = logging.getLogger(__name__)

PLOTTED = ("none", "magsac", "mop", "mop_miho", "mop_miho+ncc", "mop_miho+track", "adalam", "colmap")


def plot_error_distribution(path: Path, frontend: str, kept_errors: dict[str, list[np.ndarray]]) -> None:
    """Cumulative distribution of the GT error (epipolar or transfer, pixels) of the matches
    each stage keeps, over every pair of the run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    bins = np.logspace(-2, 2.5, 200)
    for name, chunks in kept_errors.items():
        if name not in PLOTTED or not chunks:
            continue
        e = np.concatenate(chunks)
        if e.size == 0:
            continue
        share = np.searchsorted(np.sort(e), bins, side="right") / e.size
        ax.plot(bins, share, label=f"{name} ({e.size} matches)", lw=1.4)
    ax.set_xscale("log")
    ax.set_xlabel("GT error of kept matches (px, log scale)")
    ax.set_ylabel("share of kept matches with error <= x")
    ax.set_title(f"Error distribution before and after each stage - {frontend}")
    ax.axvline(3.0, color="grey", lw=0.8, ls="--")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_benchmark(data_root: Path, out_dir: Path, *, frontends=("sift",), datasets=tuple(DATASETS),
                  quick: bool = False, pair_limit: int | None = None, pipelines: list[str] | None = None,
                  cache_dir: Path | None = None, seed: int = 0, progress: bool = True) -> dict:
    """Evaluate every pipeline on every pair; write ``<frontend>.md/.json/_errors.png``.

    Args:
        data_root: the ``shared/data`` folder.
        out_dir: where results go (created).
        quick: a few pipelines and one pair per scene folder (CI mode, minutes).
        pair_limit: at most this many pairs per scene folder (None: all; quick: 1).
    Returns:
        ``{frontend: {dataset: {pipeline: summary}}}``.
    """
    from tqdm import tqdm

    data_root, out_dir = Path(data_root), Path(out_dir)
    cache_dir = Path(cache_dir) if cache_dir else out_dir / "cache"
    names = pipelines or pipeline_names(quick)
    limit = 1 if quick and pair_limit is None else pair_limit
    everything = {}
    for frontend in frontends:
        results: dict[str, dict] = {}
        kept_errors: dict[str, list[np.ndarray]] = {n: [] for n in names}
        for dataset in datasets:
            pairs = load_pairs(data_root, dataset, limit)
            outcomes: dict[str, list] = {n: [] for n in names}
            bar = tqdm(pairs, desc=f"{frontend}/{dataset}", disable=not progress, leave=False)
            for pair in bar:
                inp = load_inputs(pair, frontend, cache_dir)
                err_in = gt_error(pair, inp.pts1, inp.pts2)
                for name in names:
                    try:
                        outcome, errs = evaluate_pipeline(name, inp, err_in, seed=seed)
                    except Exception as exc:  # a crash in one pipeline must not hide the others
                        log.error("%s on %s (%s) failed: %s", name, pair.label, frontend, exc)
                        raise
                    outcomes[name].append(outcome)
                    kept_errors[name].append(errs)
            results[dataset] = {n: summarize(o) for n, o in outcomes.items()}
        md, js = write_results(out_dir, frontend, results)
        plot_error_distribution(out_dir / f"{frontend}_errors.png", frontend, kept_errors)
        log.info("wrote %s, %s", md, js)
        everything[frontend] = results
    return everything


def headline(results: dict, pipelines=("none", "magsac", "mop_miho", "mop_miho+ncc", "mop_miho+track", "adalam", "colmap")) -> str:
    """A short table for the README: mean AUC^F_M (or AUC^H) per dataset and front end."""
    lines = []
    for frontend, per_dataset in results.items():
        datasets = list(per_dataset)
        lines.append(f"| {frontend} | " + " | ".join(datasets) + " |")
        lines.append("|---|" + "---|" * len(datasets))
        for p in pipelines:
            cells = []
            for d in datasets:
                s = per_dataset[d].get(p)
                if not s:
                    cells.append("")
                    continue
                auc = s.get("auc_H") or s.get("auc_F_magsac")
                cells.append(f"{100 * mean_auc(auc):.1f}")
            if any(cells):
                lines.append(f"| {p} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def save_summary(out_dir: Path, results: dict, seconds: float) -> Path:
    path = Path(out_dir) / "summary.json"
    path.write_text(json.dumps({"seconds": seconds, "results": results}, indent=1, default=float))
    return path
