"""Speed and accuracy of the pairwise NCC refinement (``colmap_miho.refine_pair``).

Matches: SIFT+NNR (8000 RootSIFT, mutual NN, ratio 0.95: the paper's front end) and a
corner-like front end (GFTT + SIFT descriptors) on Oxford pairs with GT homographies. Patch
homographies: the GT pair (I, H^-1), so that the figures measure NCC itself, not the filter.

Accuracy: median two-way transfer error under GT of the GT-consistent matches (< 3 px)
before and after refinement, per perturbation set ("none": extended pair + base pair, 2
shapes; "small": 5 + 1; "paper": 25 + 1, the shape chosen coarse-to-fine; "paper-x": the same
25 + 1 searched exhaustively at full resolution, like the reference), for move="auto" (both
directions, the paper's) and move="2" (one direction, as in the track walk).

Speed: median wall time of ``--runs`` calls at the reference's two sizes (950 and 2549
matches: the SIFT matches of a pair tiled to that count), and the process CPU time divided by
the torch thread count, a better estimate of an idle machine's wall time when other jobs share
the CPU (with spinning OpenMP threads on an oversubscribed machine, CPU time is inflated too:
use ``--threads 1`` there, whose CPU time is the work of one core). Reference implementation
on this machine class (algorithm.md): full NCC (25 shapes + base, both directions) 5.4 s for 950 matches
and 21 s for 2549.

    python benchmarks/bench_ncc.py            # graf and boat 1->2, both front ends, 3 runs
    python benchmarks/bench_ncc.py --quick    # graf 1->2, SIFT, 1 run, 950 matches only
    python benchmarks/bench_ncc.py --threads 1 --skip-accuracy   # timings on a busy machine

Data: ``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from colmap_miho import refine_pair
from colmap_miho.refinement.config import NCCConfig
from miho_bench.datasets import oxford_pairs
from miho_bench.frontend import sift_matches
from miho_bench.match_errors import transfer_error
from miho_bench.variants import variant

GT_PX = 3.0
REFERENCE_S = {950: 5.4, 2549: 21.0}


def data_root() -> Path:
    env = os.environ.get("COLMAP_MIHO_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


def timed(fn, runs: int) -> tuple[float, float]:
    walls, cpus = [], []
    for _ in range(runs):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus) / torch.get_num_threads()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one pair, SIFT only, one run")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--skip-accuracy", action="store_true", help="timings only")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    root = data_root()
    if not (root / "oxford_affine").is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 2
    runs = 1 if args.quick else args.runs
    seqs = ["graf"] if args.quick else ["graf", "boat"]
    detectors = ["sift"] if args.quick else ["sift", "gftt"]
    sizes = [950] if args.quick else [950, 2549]
    # (label, perturbation set, coarse-to-fine shape choice); "paper-x" searches all 25 shapes
    # at every offset at full resolution, as the reference does
    variants = {"none": ("none", True), "small": ("small", True), "paper": ("paper", True),
                "paper-x": ("paper", False)}
    sets = list(variants)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")

    print("\n== accuracy: median GT transfer error (px) of GT-consistent matches ==")
    print(f"{'pair':14s} {'front end':9s} {'n':>5s} {'before':>7s} "
          + " ".join(f"{s + '/' + m:>11s}" for s in sets for m in ("auto", "2")))
    timing_input = None
    if args.skip_accuracy:
        seqs, detectors = seqs[:1], ["sift"]
    for seq in seqs:
        pair = oxford_pairs(root / "oxford_affine" / seq, targets=(2,))[0]
        img1, img2 = pair.image1(), pair.image2()
        for det in detectors:
            fm = sift_matches(img1, img2, detector=det, max_features=8000)
            err0 = transfer_error(pair.H_2from1, fm.pts1, fm.pts2)
            good = err0 < GT_PX
            p1, p2 = fm.pts1[good], fm.pts2[good]
            homs = np.tile(np.stack([np.eye(3), np.linalg.inv(pair.H_2from1)]), (len(p1), 1, 1, 1))
            cells = []
            for s in ([] if args.skip_accuracy else sets):
                for move in ("auto", "2"):
                    shapes, coarse = variants[s]
                    r = refine_pair(img1, img2, p1, p2, homs, move=move,
                                    config=variant(NCCConfig.pairwise(device=args.device),
                                                   perturbations=shapes, coarse_shapes=coarse))
                    cells.append(f"{np.median(transfer_error(pair.H_2from1, r.pts1, r.pts2)):11.3f}")
            if cells:
                print(f"{seq + ' 1-2':14s} {det:9s} {len(p1):5d} {np.median(err0[good]):7.3f} "
                      + " ".join(cells))
            if timing_input is None and det == "sift":
                all_homs = np.tile(np.stack([np.eye(3), np.linalg.inv(pair.H_2from1)]),
                                   (len(fm.pts1), 1, 1, 1))
                timing_input = (img1, img2, fm.pts1, fm.pts2, all_homs)

    print(f"\n== speed: median wall s (CPU s / threads), {torch.get_num_threads()} thread(s) ==")
    img1, img2, p1, p2, homs = timing_input
    print(f"{'matches':>7s} {'set':7s} {'move':5s} {'wall':>7s} {'cpu/thr':>8s} {'ref':>6s} "
          f"{'x wall':>7s} {'x cpu':>7s}")
    for n in sizes:
        idx = np.resize(np.arange(len(p1)), n)
        for s in sets:
            for move in ("auto", "2"):
                shapes, coarse = variants[s]
                cfg = variant(NCCConfig.pairwise(device=args.device), perturbations=shapes, coarse_shapes=coarse)
                wall, cpu = timed(lambda idx=idx, move=move, cfg=cfg: refine_pair(
                    img1, img2, p1[idx], p2[idx], homs[idx], move=move, config=cfg), runs)
                ref = REFERENCE_S[n]
                print(f"{n:7d} {s:7s} {move:5s} {wall:7.2f} {cpu:8.2f} {ref:6.1f} "
                      f"{ref / wall:7.1f} {ref / cpu:7.1f}")
    print("\nref: the reference implementation's full NCC (25 shapes + base, both directions) on "
          "this machine class; x wall / x cpu: ref divided by our wall or CPU-per-thread time "
          "(only the paper and paper-x rows with move auto run the same shapes; paper chooses the "
          "shape on a stride-2 grid first, paper-x searches every shape at every offset). "
          "Timings taken while other jobs share the CPU are pessimistic.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
