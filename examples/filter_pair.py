"""Filter the SIFT matches of one Oxford pair with MOP+MiHo and print what was found.

    python examples/filter_pair.py [graf|boat|bikes|leuven] [2..6]

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
    env = os.environ.get("COLMAP_MIHO_DATA")
    root = Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"
    seq_dir = root / "oxford_affine" / seq
    if not seq_dir.is_dir():
        print(f"skipped: no Oxford sequence at {seq_dir} (set COLMAP_MIHO_DATA)")
        return 0

    from colmap_miho import filter_matches
    from miho_bench.datasets import oxford_pairs
    from miho_bench.frontend import sift_matches
    from miho_bench.match_errors import transfer_error

    pair = oxford_pairs(seq_dir, (target,))[0]
    m = sift_matches(pair.image1(), pair.image2())  # SIFT+NNR, (x, y) pixel centres
    res = filter_matches(m.pts1, m.pts2, method="mop_miho", seed=0)

    err = transfer_error(pair.H_2from1, m.pts1, m.pts2)  # vs the GT homography
    good = err <= 3.0
    kept = res.inliers
    print(f"{seq} img1 -> img{target}: {len(kept)} SIFT+NNR matches, {good.mean():.1%} within 3 px of GT")
    print(f"MOP+MiHo: success={res.success}, {res.num_homographies} homographies, "
          f"{res.num_inliers} matches kept in {res.stats['time_total']:.3f} s")
    print(f"  precision {np.mean(good[kept]):.3f} (was {good.mean():.3f}), "
          f"recall {np.sum(good & kept) / good.sum():.3f}")
    for k, H in enumerate(res.homographies):
        print(f"  H{k}: {np.sum(res.labels == k):4d} matches, support {res.stats['support'][k]:4d}, "
              f"H[0] = {np.array2string(H[0], precision=3)}")
    A, B = res.patch_homographies[0]
    sel = res.labels == 0
    a = np.c_[m.pts1[sel], np.ones(sel.sum())] @ A.T
    b = np.c_[m.pts2[sel], np.ones(sel.sum())] @ B.T
    gap = np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:], axis=1)
    print(f"  cluster 0 in the midpoint frame: median gap {np.median(gap):.2f} px between A x1 and B x2")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
