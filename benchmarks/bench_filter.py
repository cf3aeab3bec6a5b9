"""Speed and accuracy of the MOP / MOP+MiHo filter on real pairs with ground truth.

For each pair: SIFT+NNR matches (8000 RootSIFT, upright, mutual NN, ratio 0.95 — the
paper's front end, :func:`miho_bench.frontend.sift_matches`, cached under
``benchmarks/results/cache``), then every method;
prints the match count, homographies found, kept matches, correct kept matches (``ok``),
precision and recall against GT
(3 px: max two-way transfer error for Oxford, max epipolar distance for Strecha; recall
relative to the input's GT inliers) and the median wall time of ``--runs`` calls.

Reference implementation on this machine class (algorithm.md): MOP+MiHo 2.3 s and MOP 1.4 s
on 1351 SIFT matches; MOP+MiHo 2.5 s on 2558.

    python benchmarks/bench_filter.py            # 12 Oxford + 8 Strecha pairs
    python benchmarks/bench_filter.py --quick    # 3 pairs
    python benchmarks/bench_filter.py --sampling both   # guided vs the paper's uniform sampling
    python benchmarks/bench_filter.py --only fountain --methods mop_miho \
        --variant half:miho_threshold=half                # config overrides beside the default
    python benchmarks/bench_filter.py --device torch-cpu --torch-threads 1 --runs 1
        # the torch path (cuda, cuda:1, or torch-cpu: torch.device("cpu")); every
        # pair also runs on numpy: ``np sec`` is its time, ``same`` the share of matches with
        # the same inlier flag, ``lab`` with the same label

Data: ``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data``. Timings taken while other jobs
share the CPU are pessimistic: the ``cpu`` column (process CPU time; the filter is
single-threaded numpy) is then the better estimate of the time on an idle machine.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from bench_hard_pairs import parse_variant

from colmap_miho import filter_matches
from colmap_miho.filtering.config import FilterConfig
from miho_bench.datasets import multiview_pairs, oxford_pairs
from miho_bench.frontend_cache import load_inputs
from miho_bench.match_errors import gt_error
from miho_bench.variants import configured

GT_PX = 3.0
CACHE = Path(__file__).resolve().parent / "results" / "cache"


def data_root() -> Path:
    env = os.environ.get("COLMAP_MIHO_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


def select_pairs(root: Path, quick: bool):
    pairs = []
    seqs = ["graf", "boat"] if quick else ["graf", "boat", "bikes", "leuven"]
    for seq in seqs:
        targets = (2,) if quick else (2, 3, 4)
        pairs += [(f"{seq} {p.name1}-{p.name2}", p) for p in oxford_pairs(root / "oxford_affine" / seq, targets)]
    for scene in ["strecha_fountain_p11"] if quick else ["strecha_fountain_p11", "strecha_entry_p10"]:
        mv = multiview_pairs(root / scene)
        first = [p for p in mv if p.name1 == mv[0].name1][: 1 if quick else 4]
        pairs += [(f"{scene.split('_')[1]} {p.name1}-{p.name2}", p) for p in first]
    return pairs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 pairs only")
    ap.add_argument("--runs", type=int, default=5, help="timed calls per pair and method")
    ap.add_argument("--methods", default="mop,mop_miho", help="comma-separated methods")
    ap.add_argument("--sampling", choices=("local", "uniform", "both"), default="local")
    ap.add_argument("--variant", action="append", default=[],
                    help="extra config per method, 'name:key=value,...' (repeatable)")
    ap.add_argument("--only", default=None, help="only pairs whose label contains this")
    ap.add_argument("--device", default="cpu",
                    help="filter_matches device: cpu (numpy), cuda[:N], torch-cpu (torch.device('cpu'), "
                         "the torch path on the CPU) (default cpu)")
    ap.add_argument("--torch-threads", type=int, default=0,
                    help="torch.set_num_threads for the torch path (0: torch's default)")
    args = ap.parse_args(argv)
    compare = args.device != "cpu"
    device = args.device
    if device == "torch-cpu":
        import torch

        device = torch.device("cpu")
    if compare and args.torch_threads:
        import torch

        torch.set_num_threads(args.torch_threads)
    root = data_root()
    if not (root / "README.md").is_file():
        print(f"data folder not found at {root} (set COLMAP_MIHO_DATA)")
        return 1
    samplings = ["local", "uniform"] if args.sampling == "both" else [args.sampling]
    extra = [("", {})] + [parse_variant(v) for v in args.variant]
    variants = [(m, s, vn, over) for m in args.methods.split(",") for s in samplings
                for vn, over in extra]
    # Warm-up (imports, first-call overheads) outside the timings.
    rng = np.random.default_rng(0)
    filter_matches(rng.uniform(0, 500, (100, 2)), rng.uniform(0, 500, (100, 2)),
                   device=device)
    print(f"{'pair':<28} {'N':>5} {'inP':>5} | {'method':<16} {'K':>3} {'kept':>5} "
          f"{'ok':>5} {'P':>6} {'R':>6} {'sec':>6} {'cpu':>6}"
          + (f" {'np sec':>6} {'same':>6} {'lab':>6}" if compare else ""))
    agree: dict[tuple[str, str], list[tuple[int, int, int, float]]] = {}
    summary: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    for label, pair in select_pairs(root, args.quick):
        if args.only and args.only not in label:
            continue
        fm = load_inputs(pair, "sift", CACHE)  # sift_matches(), cached on disk
        err = gt_error(pair, fm.pts1, fm.pts2)
        good = err <= GT_PX
        for method, sampling, vname, over in variants:
            cfg = configured(FilterConfig, method=method, sampling=sampling, **over)
            name = method if len(samplings) == 1 else f"{method}/{sampling}"
            name += f"/{vname}" if vname else ""
            times, cpu = [], []
            for _ in range(args.runs):
                t0, c0 = time.perf_counter(), time.process_time()
                res = filter_matches(fm.pts1, fm.pts2, config=cfg, seed=0, device=device)
                sync(device)
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            extra = ""
            if compare:
                np_times = []
                for _ in range(args.runs):
                    t0 = time.perf_counter()
                    ref = filter_matches(fm.pts1, fm.pts2, config=cfg, seed=0)
                    np_times.append(time.perf_counter() - t0)
                same = int(np.count_nonzero(ref.inliers == res.inliers))
                lab = int(np.count_nonzero(ref.labels == res.labels))
                np_sec = float(np.median(np_times))
                agree.setdefault((name, sampling), []).append((len(err), same, lab, np_sec))
                extra = f" {np_sec:>6.3f} {same / len(err):>6.1%} {lab / len(err):>6.1%}"
            kept = res.inliers
            # nan when nothing is kept (or the input has no correct match): left out of means
            prec = np.count_nonzero(kept & good) / kept.sum() if kept.any() else float("nan")
            rec = np.count_nonzero(kept & good) / good.sum() if good.any() else float("nan")
            sec, csec = float(np.median(times)), float(np.median(cpu))
            correct = np.count_nonzero(kept & good)
            summary.setdefault((name, sampling), []).append((prec, rec, sec, csec, correct))
            print(f"{label:<28} {len(err):>5} {good.mean():>5.3f} | {name:<16} "
                  f"{res.num_homographies:>3} {res.num_inliers:>5} {correct:>5} {prec:>6.3f} {rec:>6.3f} "
                  f"{sec:>6.3f} {csec:>6.3f}" + extra)
        sys.stdout.flush()
    print("\nmean over pairs (sec = wall, cpu = process CPU time; median per pair, then mean/max)")
    for (method, sampling), rows in summary.items():
        a = np.array(rows)
        print(f"  {method:<22} {sampling:<8} P {np.nanmean(a[:, 0]):.3f}  R {np.nanmean(a[:, 1]):.3f}  "
              f"correct kept {int(a[:, 4].sum())}  "
              f"sec mean {a[:, 2].mean():.3f} max {a[:, 2].max():.3f}  "
              f"cpu mean {a[:, 3].mean():.3f} max {a[:, 3].max():.3f}")
    for key, rows in agree.items():
        n, same, lab, np_sec = np.array(rows).T
        dev_sec = np.array([r[2] for r in summary[key]])
        print(f"  {key[0]:<22} {args.device} vs numpy: same inlier flag {same.sum() / n.sum():.4%}, "
              f"same label {lab.sum() / n.sum():.4%} of {int(n.sum())} matches; sec per pair "
              f"{args.device} {dev_sec.mean():.3f} numpy {np_sec.mean():.3f}")
    return 0


def sync(device) -> None:
    """Wait for queued CUDA work, so that wall times are complete."""
    if str(device).startswith("cuda"):
        import torch

        torch.cuda.synchronize()


if __name__ == "__main__":
    raise SystemExit(main())
