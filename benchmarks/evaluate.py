#!/usr/bin/env python
"""Reproduce the match-filtering evaluation on ../shared/data (paper protocol, Sec. 4.1.3).

    python benchmarks/evaluate.py                 # everything (all front ends, all pairs)
    python benchmarks/evaluate.py --quick         # CI mode: a few pipelines, 1 pair per scene

Writes benchmarks/results/<frontend>.md (tables in the paper's layout), .json, _errors.png
(error distribution of the kept matches per stage) and prints a headline table.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from miho_bench.benchmark import DATASETS
from miho_bench.benchmark_run import headline, run_benchmark, save_summary
from miho_bench.frontend_cache import FRONTENDS

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--cache", type=Path, default=None, help="front-end match cache (default: <out>/cache)")
    ap.add_argument("--frontends", default=None, help=f"comma list of {','.join(FRONTENDS)}")
    ap.add_argument("--datasets", default=",".join(DATASETS))
    ap.add_argument("--pairs", type=int, default=None, help="at most this many pairs per scene folder")
    ap.add_argument("--pipelines", default=None, help="comma list (default: all, or the quick set)")
    ap.add_argument("--quick", action="store_true", help="CI mode: quick pipeline set, 1 pair per scene")
    ap.add_argument("--workers", type=int, default=None, help="processes over pairs (default: all cores)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")
    if not (args.data / "README.md").is_file():
        print(f"data folder not found: {args.data}")
        return 2
    frontends = args.frontends.split(",") if args.frontends else (["sift"] if args.quick else list(FRONTENDS))
    t0 = time.perf_counter()
    results = run_benchmark(args.data, args.out, frontends=frontends, datasets=args.datasets.split(","),
                            quick=args.quick, pair_limit=args.pairs,
                            pipelines=args.pipelines.split(",") if args.pipelines else None,
                            cache_dir=args.cache, workers=args.workers)
    seconds = time.perf_counter() - t0
    save_summary(args.out, results, seconds)
    print(headline(results))
    for f in frontends:
        print((args.out / f"{f}.md").read_text())
    print(f"total {seconds:.0f} s; results in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
