"""CPU vs CUDA agreement and CUDA speed of the filter and the NCC refinement (needs CUDA).

0. ``filter_matches`` (MOP and MOP+MiHo, seed 0) on the 12 Oxford + 8 Strecha SIFT pairs of
   ``bench_filter.py`` (``--quick``: 3 pairs), numpy on the CPU against ``--device``: per
   pair and in total the share of matches with the same inlier flag and with the same label,
   and the seconds per pair of each (median of ``--runs`` calls after a warm-up); then the
   fountain-P11 scene as the pipeline filters it: pycolmap SIFT + exhaustive matching (the
   verified matches, 55 pairs, about 113k matches; the database is built once under
   ``benchmarks/results/cache``), every pair filtered with MOP+MiHo on each device in
   turn: total seconds, seconds per pair and the agreement.
1. ``refine_pair`` on Oxford graf and boat 1->2 (SIFT and GFTT front ends, GT patch
   homographies), per shape set and move mode: how often CPU and CUDA move the same side, the
   largest and median coordinate difference of matches moved on both, and the median GT
   transfer error on each device.
2. ``refine_tracks`` on the first ``--track-images`` images of Oxford graf (all pairs, SIFT
   matches filtered by MOP+MiHo): the same agreement figures per keypoint (CPU, one call per
   pair, against CUDA, one call per level: the defaults), and the time of each, also of CUDA
   with one call per pair.
3. CUDA wall time of ``refine_pair`` at the reference's sizes (950 and 2549 matches) for
   batch sizes 512 (the default) and 4096.

    python benchmarks/check_cuda.py
    python benchmarks/check_cuda.py --sections filter,fountain     # the filter only
    python benchmarks/check_cuda.py --device cpu --sections filter --quick
        # dry run without a GPU: the filter sections with torch on the CPU (torch.device("cpu"))
        # in place of CUDA (the NCC sections need CUDA and are skipped)

Carry ``benchmarks/results/cache`` (ignored by git) to skip the SIFT and pycolmap front ends.
Data: ``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data``. Exit code 2 without CUDA (unless
``--device cpu``) or data.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from colmap_miho import filter_matches, refine_pair
from colmap_miho.refinement.config import NCCConfig, TrackConfig
from colmap_miho.refinement.tracks.walk import refine_tracks
from miho_bench.datasets import oxford_pairs
from miho_bench.frontend import filtered_multiview_matches, sift_matches
from miho_bench.match_errors import transfer_error
from miho_bench.variants import variant

GT_PX = 3.0
SECTIONS = ("filter", "fountain", "pairs", "tracks", "speed")
NCC_SECTIONS = ("pairs", "tracks", "speed")


def data_root() -> Path:
    env = os.environ.get("COLMAP_MIHO_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


def agreement(a1, a2, side_a, b1, b2, side_b) -> str:
    same = float(np.mean(side_a == side_b))
    both = (side_a > 0) & (side_a == side_b)
    if not both.any():
        return f"same side {same:6.1%}, none moved on both"
    d = np.maximum(np.linalg.norm(a1 - b1, axis=1), np.linalg.norm(a2 - b2, axis=1))[both]
    return f"same side {same:6.1%}, |cpu-cuda| max {d.max():.2e} median {np.median(d):.2e} px"


def _sync(device: str | torch.device) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def _timed_filter(pts1, pts2, device: str | torch.device, runs: int, method: str = "mop_miho"):
    """(result, median seconds) of ``runs`` calls of ``filter_matches`` on ``device``."""
    walls = []
    for _ in range(runs):
        t0 = time.perf_counter()
        res = filter_matches(pts1, pts2, method=method, seed=0, device=device)
        _sync(device)
        walls.append(time.perf_counter() - t0)
    return res, statistics.median(walls)


def _same(a, b) -> tuple[int, int]:
    """Matches with the same inlier flag, with the same label."""
    return int(np.count_nonzero(a.inliers == b.inliers)), int(np.count_nonzero(a.labels == b.labels))


def check_filter(root: Path, device: str | torch.device, runs: int, quick: bool) -> None:
    from bench_filter import CACHE, select_pairs

    from miho_bench.frontend_cache import load_inputs

    print(f"== filter_matches: numpy (CPU) vs {device} (bench_filter pairs, SIFT+NNR) ==")
    rng = np.random.default_rng(0)  # warm-up: imports, kernels, allocator
    for dev in ("cpu", device):
        filter_matches(rng.uniform(0, 500, (300, 2)), rng.uniform(0, 500, (300, 2)), device=dev)
    print(f"{'pair':<28} {'N':>5} {'method':<9} {'kept np':>7} {'kept dev':>8} {'same':>7} "
          f"{'label':>7} {'np s':>6} {'dev s':>6}")
    tot: dict[str, list[float]] = {}
    for label, pair in select_pairs(root, quick):
        fm = load_inputs(pair, "sift", CACHE)
        for method in ("mop", "mop_miho"):
            a, ta = _timed_filter(fm.pts1, fm.pts2, "cpu", runs, method)
            b, tb = _timed_filter(fm.pts1, fm.pts2, device, runs, method)
            same, lab = _same(a, b)
            n = len(fm.pts1)
            for key, v in (("n", n), ("same", same), ("lab", lab), ("np", ta), ("dev", tb)):
                tot.setdefault(f"{method} {key}", []).append(v)
            print(f"{label:<28} {n:>5} {method:<9} {a.num_inliers:>7} {b.num_inliers:>8} "
                  f"{same / n:>7.2%} {lab / n:>7.2%} {ta:>6.3f} {tb:>6.3f}")
        sys.stdout.flush()
    for method in ("mop", "mop_miho"):
        n = sum(tot[f"{method} n"])
        print(f"{method}: same inlier flag {sum(tot[f'{method} same']) / n:.4%}, same label "
              f"{sum(tot[f'{method} lab']) / n:.4%} of {int(n)} matches; seconds per pair numpy "
              f"{np.mean(tot[f'{method} np']):.3f}, {device} {np.mean(tot[f'{method} dev']):.3f}")


def fountain_matches(root: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(pts1, pts2) of every verified pair of fountain-P11 from pycolmap SIFT + exhaustive
    matching (pixel centres), as the pipeline reads them."""
    from bench_filter import CACHE

    from colmap_miho.adapters.database import ColmapDatabase
    from miho_bench.frontend_cache import _colmap_database

    CACHE.mkdir(parents=True, exist_ok=True)
    db_path = _colmap_database(root / "strecha_fountain_p11" / "images", CACHE)
    out = []
    with ColmapDatabase(db_path) as db:
        kps = {r.image_id: db.keypoints(r.image_id) for r in db.images()}
        for rec in db.pairs("verified"):
            m = db.matches(rec.image_id1, rec.image_id2, "verified").astype(np.int64)
            out.append((kps[rec.image_id1][m[:, 0]], kps[rec.image_id2][m[:, 1]]))
    return out


def time_fountain(root: Path, device: str | torch.device) -> None:
    print(f"\n== filter_matches on fountain-P11 (pycolmap verified matches): numpy vs {device} ==")
    pairs = fountain_matches(root)
    print(f"{len(pairs)} pairs, {sum(len(p1) for p1, _ in pairs)} matches, MOP+MiHo, one call "
          "per pair in turn (after one warm-up call)")
    res: dict[str, list] = {}
    for name, dev in (("numpy", "cpu"), ("torch", device)):
        filter_matches(*pairs[0], seed=0, device=dev)
        _sync(dev)
        t0 = time.perf_counter()
        res[name] = [filter_matches(p1, p2, seed=0, device=dev) for p1, p2 in pairs]
        _sync(dev)
        wall = time.perf_counter() - t0
        print(f"{name + ' ' + str(dev):>10s}: {wall:6.2f} s, {wall / len(pairs):.4f} s per pair, kept "
              f"{sum(r.num_inliers for r in res[name])}")
    n = sum(len(p1) for p1, _ in pairs)
    same = [_same(a, b) for a, b in zip(res["numpy"], res["torch"], strict=True)]
    print(f"same inlier flag {sum(s for s, _ in same) / n:.4%}, same label "
          f"{sum(lab for _, lab in same) / n:.4%}; pairs identical "
          f"{sum(s == len(p1) and lab == len(p1) for (s, lab), (p1, _) in zip(same, pairs, strict=True))}"
          f"/{len(pairs)}")


def check_pairs(root: Path) -> None:
    print("== refine_pair: CPU vs CUDA (Oxford 1->2, GT patch homographies) ==")
    for seq in ("graf", "boat"):
        pair = oxford_pairs(root / "oxford_affine" / seq, targets=(2,))[0]
        img1, img2 = pair.image1(), pair.image2()
        for det in ("sift", "gftt"):
            fm = sift_matches(img1, img2, detector=det, max_features=8000)
            good = transfer_error(pair.H_2from1, fm.pts1, fm.pts2) < GT_PX
            p1, p2 = fm.pts1[good], fm.pts2[good]
            homs = np.tile(np.stack([np.eye(3), np.linalg.inv(pair.H_2from1)]), (len(p1), 1, 1, 1))
            for shapes, move in itertools.product(("none", "paper"), ("auto", "2")):
                res = {dev: refine_pair(img1, img2, p1, p2, homs, move=move,
                                        config=variant(NCCConfig.pairwise(device=dev), perturbations=shapes))
                       for dev in ("cpu", "cuda")}
                c, g = res["cpu"], res["cuda"]
                err = {k: np.median(transfer_error(pair.H_2from1, r.pts1, r.pts2))
                       for k, r in res.items()}
                print(f"{seq} {det:4s} n={len(p1):4d} {shapes:5s}/{move:4s} GT err cpu "
                      f"{err['cpu']:.3f} cuda {err['cuda']:.3f} px; "
                      + agreement(c.pts1, c.pts2, c.moved_side, g.pts1, g.pts2, g.moved_side))


def check_tracks(root: Path, n_images: int) -> None:
    print(f"\n== refine_tracks: CPU vs CUDA (Oxford graf images 1-{n_images}, all pairs) ==")
    seq = root / "oxford_affine" / "graf"
    import cv2

    images = {i: cv2.imread(str(next(seq.glob(f"img{i}.*"))), cv2.IMREAD_GRAYSCALE)
              for i in range(1, n_images + 1)}
    keypoints, matches, results = filtered_multiview_matches(images)
    print(f"{len(matches)} pairs, {sum(len(m) for m in matches.values())} kept matches")
    out = {}
    runs = {"cpu": ("cpu", None), "cuda per pair": ("cuda", False), "cuda": ("cuda", None)}
    for name, (dev, batch) in runs.items():
        refine_tracks(images, keypoints, matches, results, ncc_config=NCCConfig.pairwise(device=dev),
                      track_config=variant(TrackConfig(), batch_pairs=batch))  # warm-up
        t0 = time.perf_counter()
        out[name] = refine_tracks(images, keypoints, matches, results,
                                  ncc_config=NCCConfig.pairwise(device=dev),
                                  track_config=variant(TrackConfig(), batch_pairs=batch))
        st = out[name].stats
        print(f"{name:13s}: {time.perf_counter() - t0:6.2f} s, {st['refine_calls']} calls, "
              f"tracks {st['tracks']}, refined {st['refined']}, moved {st['moved']}, "
              f"rejected {st['rejected']}")
    for i in sorted(images):
        a, b = out["cpu"].keypoints[i], out["cuda"].keypoints[i]
        ma, mb = out["cpu"].displacement[i] > 0, out["cuda"].displacement[i] > 0
        d = np.linalg.norm(a - b, axis=1)
        print(f"image {i}: moved cpu {int(ma.sum())} cuda {int(mb.sum())}, same flag "
              f"{np.mean(ma == mb):6.1%}, |cpu-cuda| max {d.max():.2e} median over moved "
              f"{np.median(d[ma & mb]) if (ma & mb).any() else 0:.2e} px")


def time_cuda(root: Path, runs: int) -> None:
    print("\n== CUDA speed: median wall s of refine_pair (graf 1->2 SIFT matches tiled) ==")
    pair = oxford_pairs(root / "oxford_affine" / "graf", targets=(2,))[0]
    img1, img2 = pair.image1(), pair.image2()
    fm = sift_matches(img1, img2, detector="sift", max_features=8000)
    homs = np.tile(np.stack([np.eye(3), np.linalg.inv(pair.H_2from1)]), (len(fm.pts1), 1, 1, 1))
    g1, g2 = (torch.as_tensor(im, device="cuda") for im in (img1, img2))
    print(f"{'matches':>7s} {'set':6s} {'move':5s} {'batch':>6s} {'numpy in':>9s} {'cuda in':>8s}")
    for n in (950, 2549):
        idx = np.resize(np.arange(len(fm.pts1)), n)
        for shapes, move, batch in itertools.product(("none", "paper"), ("auto", "2"),
                                                      (512, 4096)):
            cfg = variant(NCCConfig.pairwise(device="cuda", batch_size=batch), perturbations=shapes)
            cells = []
            for a, b in ((img1, img2), (g1, g2)):
                def call(a=a, b=b, idx=idx, move=move, cfg=cfg):
                    refine_pair(a, b, fm.pts1[idx], fm.pts2[idx], homs[idx], move=move, config=cfg)
                call()  # warm-up (kernels, allocator)
                walls = []
                for _ in range(runs):
                    t0 = time.perf_counter()
                    call()
                    torch.cuda.synchronize()
                    walls.append(time.perf_counter() - t0)
                cells.append(statistics.median(walls))
            print(f"{n:7d} {shapes:6s} {move:5s} {batch:6d} {cells[0]:9.3f} {cells[1]:8.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--track-images", type=int, default=4)
    ap.add_argument("--device", choices=("cuda", "cpu"), default="cuda",
                    help="cpu: dry run of the filter sections with torch on the CPU")
    ap.add_argument("--sections", default=",".join(SECTIONS),
                    help=f"comma-separated, of {', '.join(SECTIONS)} (default: all)")
    ap.add_argument("--quick", action="store_true", help="filter section: 3 pairs only")
    args = ap.parse_args(argv)
    sections = args.sections.split(",")
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        ap.error(f"unknown sections {unknown}; choose from {', '.join(SECTIONS)}")
    if args.device == "cuda" and not torch.cuda.is_available():
        print("torch sees no CUDA device", file=sys.stderr)
        return 2
    root = data_root()
    if not (root / "oxford_affine").is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 2
    device = "cuda" if args.device == "cuda" else torch.device("cpu")
    if args.device == "cpu":
        skipped = [s for s in sections if s in NCC_SECTIONS]
        sections = [s for s in sections if s not in NCC_SECTIONS]
        torch.set_num_threads(1)  # like the single-threaded numpy filter; no contention
        print(f"dry run: torch {torch.__version__} on the CPU (1 thread) in place of CUDA"
              + (f"; skipped (need CUDA): {', '.join(skipped)}" if skipped else ""))
    else:
        print(f"torch {torch.__version__}, {torch.cuda.get_device_name()}")
    if "filter" in sections:
        check_filter(root, device, args.runs, args.quick)
    if "fountain" in sections:
        time_fountain(root, device)
    if "pairs" in sections:
        check_pairs(root)
    if "tracks" in sections:
        check_tracks(root, args.track_images)
    if "speed" in sections:
        time_cuda(root, args.runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
