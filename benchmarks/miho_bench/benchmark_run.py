"""Run the match-filtering benchmark and write its tables, JSON and plots.

``benchmarks/evaluate.py`` is the command line; :func:`run_benchmark` is what a test calls in
quick mode.
"""

from __future__ import annotations

import json
import logging
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
    from colmap_miho.extras import require

    require("matplotlib", "plots", "the benchmark's plots").use("Agg")
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


def _init_worker() -> None:
    """One torch thread per worker process: two processes on two cores beat two threads."""
    import torch

    torch.set_num_threads(1)


def _evaluate_pair(pair, frontend: str, cache_dir: Path, names: list[str], seed: int):
    """All pipelines on one pair (runs in a worker process)."""
    inp = load_inputs(pair, frontend, cache_dir)
    err_in = gt_error(pair, inp.pts1, inp.pts2)
    out = {}
    for name in names:
        try:
            out[name] = evaluate_pipeline(name, inp, err_in, seed=seed)
        except Exception as exc:  # name the pair and pipeline, then fail loudly
            raise RuntimeError(f"{name} on {pair.label} ({frontend}) failed: {exc}") from exc
    return out


def run_benchmark(data_root: Path, out_dir: Path, *, frontends=("sift",), datasets=tuple(DATASETS),
                  quick: bool = False, pair_limit: int | None = None, pipelines: list[str] | None = None,
                  cache_dir: Path | None = None, seed: int = 0, progress: bool = True,
                  workers: int | None = None) -> dict:
    """Evaluate every pipeline on every pair; write ``<frontend>.md/.json/_errors.png``.

    Args:
        data_root: the ``shared/data`` folder.
        out_dir: where results go (created).
        quick: a few pipelines and one pair per scene folder (CI mode, minutes).
        pair_limit: at most this many pairs per scene folder (None: all; quick: 1).
        workers: processes evaluating pairs in parallel (default: all cores; 1 = in process).
    Returns:
        ``{frontend: {dataset: {pipeline: summary}}}``.
    """
    import os
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    data_root, out_dir = Path(data_root), Path(out_dir)
    cache_dir = Path(cache_dir) if cache_dir else out_dir / "cache"
    names = pipelines or pipeline_names(quick)
    limit = 1 if quick and pair_limit is None else pair_limit
    workers = workers or os.cpu_count() or 1
    everything = {}
    for frontend in frontends:
        if frontend == "colmap":  # build the per-scene databases once, before the workers start
            for dataset in datasets:
                for pair in load_pairs(data_root, dataset, limit):
                    load_inputs(pair, frontend, cache_dir)
        results: dict[str, dict] = {}
        kept_errors: dict[str, list[np.ndarray]] = {n: [] for n in names}
        for dataset in datasets:
            pairs = load_pairs(data_root, dataset, limit)
            outcomes: dict[str, list] = {n: [] for n in names}
            args = [(p, frontend, cache_dir, names, seed) for p in pairs]
            if workers > 1 and len(pairs) > 1:
                import multiprocessing

                ctx = multiprocessing.get_context("spawn")
                with ProcessPoolExecutor(min(workers, len(pairs)), mp_context=ctx, initializer=_init_worker) as pool:
                    per_pair = list(tqdm(pool.map(_evaluate_pair, *zip(*args, strict=True)), total=len(pairs),
                                         desc=f"{frontend}/{dataset}", disable=not progress, leave=False))
            else:
                per_pair = [_evaluate_pair(*a) for a in tqdm(args, desc=f"{frontend}/{dataset}",
                                                             disable=not progress, leave=False)]
            for res in per_pair:  # pool.map keeps the pairs' order: results are deterministic
                for name, (outcome, errs) in res.items():
                    outcomes[name].append(outcome)
                    kept_errors[name].append(errs)
            results[dataset] = {n: summarize(o) for n, o in outcomes.items()}
        md, js = write_results(out_dir, frontend, results)
        plot_error_distribution(out_dir / f"{frontend}_errors.png", frontend, kept_errors)
        log.info("wrote %s, %s", md, js)
        everything[frontend] = results
    return everything


HEADLINE_PIPELINES = ("none", "magsac", "mop_miho", "mop_miho+ncc", "mop_miho+track", "adalam", "colmap")


def headline(results: dict, pipelines=HEADLINE_PIPELINES) -> str:
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
