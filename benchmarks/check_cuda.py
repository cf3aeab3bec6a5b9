"""CPU vs CUDA agreement and CUDA speed of the NCC refinement (needs a CUDA device).

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

Data: ``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data``. Exit code 2 without CUDA or data.
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

from colmap_miho import refine_pair
from colmap_miho.refinement.config import NCCConfig, TrackConfig
from colmap_miho.refinement.tracks import refine_tracks
from miho_bench.datasets import oxford_pairs
from miho_bench.frontend import filtered_multiview_matches, sift_matches
from miho_bench.match_errors import transfer_error

GT_PX = 3.0


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
                                        config=NCCConfig(perturbations=shapes, device=dev))
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
        refine_tracks(images, keypoints, matches, results, ncc_config=NCCConfig(device=dev),
                      track_config=TrackConfig(batch_pairs=batch))  # warm-up
        t0 = time.perf_counter()
        out[name] = refine_tracks(images, keypoints, matches, results,
                                  ncc_config=NCCConfig(device=dev),
                                  track_config=TrackConfig(batch_pairs=batch))
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
            cfg = NCCConfig(perturbations=shapes, device="cuda", batch_size=batch)
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
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("torch sees no CUDA device", file=sys.stderr)
        return 2
    root = data_root()
    if not (root / "oxford_affine").is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 2
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name()}")
    check_pairs(root)
    check_tracks(root, args.track_images)
    time_cuda(root, args.runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
