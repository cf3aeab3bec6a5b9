"""Filter one Oxford pair with MOP+MiHo, refine the kept matches by NCC, compare with GT.

    python examples/refine_pair.py [graf|boat|bikes|leuven] [2..6] [sift|gftt]

Data: ``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data`` (skips politely when absent).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> int:
    seq = argv[0] if argv else "graf"
    target = int(argv[1]) if len(argv) > 1 else 2
    detector = argv[2] if len(argv) > 2 else "gftt"
    env = os.environ.get("COLMAP_MIHO_DATA")
    root = Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"
    seq_dir = root / "oxford_affine" / seq
    if not seq_dir.is_dir():
        print(f"skipped: no Oxford sequence at {seq_dir} (set COLMAP_MIHO_DATA)")
        return 0

    from colmap_miho import NCCConfig, filter_matches, refine_pair
    from miho_bench.datasets import oxford_pairs
    from miho_bench.frontend import sift_matches
    from miho_bench.match_errors import transfer_error

    pair = oxford_pairs(seq_dir, (target,))[0]
    img1, img2 = pair.image1(), pair.image2()  # (H, W) uint8
    m = sift_matches(img1, img2, detector=detector)  # (x, y) pixel centres
    res = filter_matches(m.pts1, m.pts2, method="mop_miho", seed=0)
    kept = res.inliers
    pts1, pts2 = m.pts1[kept], m.pts2[kept]
    homs = res.patch_homographies[res.labels[kept]]  # (N, 2, 3, 3): A x1 ~ B x2

    ref = refine_pair(img1, img2, pts1, pts2, homs, move="auto", config=NCCConfig.pairwise())
    before = transfer_error(pair.H_2from1, pts1, pts2)
    after = transfer_error(pair.H_2from1, ref.pts1, ref.pts2)
    good = before <= 3.0  # GT-consistent matches
    s = ref.stats
    print(f"{seq} img1 -> img{target}, {detector}: {len(m.pts1)} matches, {kept.sum()} kept by MOP+MiHo")
    print(f"NCC ({s['shapes']} shapes x {s['directions']} directions) in {s['seconds']:.2f} s: "
          f"{s['moved']} moved, {s['rejected_border'] + s['rejected_weak']} rejected, "
          f"{s['outside']} too close to the border")
    print(f"median GT transfer error of the {good.sum()} GT-consistent matches: "
          f"{np.median(before[good]):.3f} px -> {np.median(after[good]):.3f} px")
    print(f"within 1 px of GT: {np.mean(before <= 1):.1%} -> {np.mean(after <= 1):.1%} of the kept matches")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
