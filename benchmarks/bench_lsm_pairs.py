"""Pairwise refinement with and without least-squares matching on planar pairs with a GT homography.

Pairs: Oxford affine graf, boat, bikes and leuven, img1 -> img2..img6 (``--targets``); matches:
OpenCV SIFT + RootSIFT, mutual NN, ratio 0.95 (:func:`miho_bench.frontend.sift_matches`),
then MOP+MiHo (``filter_matches``); the matches it keeps that are within 3 px of GT (max
two-way transfer error) are refined by ``refine_pair`` with the filter's patch homography
pairs (``--homographies filter``, what a user of the Python API does) or the GT pair
(I, H^-1) (``gt``: the refiner alone). Per pair: the median GT transfer error before, after
NCC (``NCCConfig.pairwise()`` with ``--set`` overrides) and after NCC + LSM (the same with
``lsm.enabled=true``), and the ratio after / before; pairs with fewer than ``--min-matches`` are
listed but not counted in the summary.

    python benchmarks/bench_lsm_pairs.py [--homographies filter|gt] [--targets 2 3 4]
        [--set template_radius=6 --set lsm.max_sigma_px=0.1]
        [--variant NAME:lsm.antialias=0.5,lsm.max_shift_px=2.0 ...]

Each ``--variant`` adds a column: the LSM configuration with its own overrides (``NCCConfig``
fields, ``lsm.*`` / ``rectify.*`` and the class constants of either).

Data: ``$COLMAP_MIHO_DATA`` or ``<repo>/../shared/data``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from colmap_miho import filter_matches, refine_pair
from colmap_miho.refinement.config import NCCConfig
from miho_bench.datasets import oxford_pairs
from miho_bench.frontend import sift_matches
from miho_bench.match_errors import transfer_error
from miho_bench.variants import configured

GT_PX = 3.0
SEQUENCES = ("graf", "boat", "bikes", "leuven")


def data_root() -> Path:
    env = os.environ.get("COLMAP_MIHO_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


def parse_sets(items: list[str]) -> dict:
    """``KEY=VALUE`` strings -> {KEY: value}, values read as true/false, int, float or text."""
    out: dict = {}
    for item in items:
        key, _, value = item.partition("=")
        low = value.lower()
        if low in ("true", "false", "yes", "no"):
            out[key] = low in ("true", "yes")
            continue
        for kind in (int, float, str):
            try:
                out[key] = kind(value)
                break
            except ValueError:
                continue
    return out


def _config(base: NCCConfig, sets: dict) -> NCCConfig:
    """``base`` with ``sets``: NCCConfig fields, ``lsm.FIELD`` / ``rectify.FIELD`` of its tables,
    and class constants (:func:`miho_bench.variants.configured`)."""
    tables = {t: {k.split(".", 1)[1]: v for k, v in sets.items() if k.startswith(t + ".")} for t in ("lsm", "rectify")}
    rest = {k: v for k, v in sets.items() if "." not in k}
    nested = {t: configured(type(getattr(base, t)), getattr(base, t), **kv) for t, kv in tables.items() if kv}
    return configured(NCCConfig, base, **nested, **rest)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--homographies", choices=["filter", "gt"], default="filter")
    ap.add_argument("--targets", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    ap.add_argument("--sequences", nargs="+", default=list(SEQUENCES))
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="FIELD=VALUE",
                    help="NCCConfig override for both runs (repeatable)")
    ap.add_argument("--variant", dest="variants", action="append", default=[],
                    metavar="NAME:FIELD=VALUE,...", help="one more LSM column (repeatable)")
    ap.add_argument("--min-matches", type=int, default=50)
    args = ap.parse_args(argv)
    root = data_root() / "oxford_affine"
    if not root.is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 2
    base = _config(NCCConfig.pairwise(device="cpu"), parse_sets(args.sets))
    lsm = _config(base, {"lsm.enabled": True})
    cfgs = {"ncc": base, "lsm": lsm}
    for item in args.variants:
        name, _, sets = item.partition(":")
        cfgs[name] = _config(lsm, parse_sets([s for s in sets.split(",") if s]))
    extra_names = list(cfgs)[2:]
    print(f"patch homographies: {args.homographies}; NCCConfig overrides: {args.sets or 'none'}; "
          f"variants: {args.variants or 'none'}")
    print(f"{'pair':12s} {'n':>5s} {'before':>7s} {'ncc':>7s} {'lsm':>7s} {'ncc/bef':>8s} "
          f"{'lsm/bef':>8s} {'lsm/ncc':>8s} applied/moved"
          + "".join(f" {name + '/bef':>10s}" for name in extra_names))
    ratios: dict[str, list[float]] = {name: [] for name in cfgs}
    worse = dict.fromkeys(cfgs, 0)
    for seq in args.sequences:
        for pair in oxford_pairs(root / seq, targets=tuple(args.targets)):
            img1, img2 = pair.image1(), pair.image2()
            fm = sift_matches(img1, img2, max_features=8000)
            fr = filter_matches(fm.pts1, fm.pts2, method="mop_miho", seed=0)
            keep = fr.labels >= 0 if fr.success else np.zeros(len(fm.pts1), bool)
            err0 = transfer_error(pair.H_2from1, fm.pts1, fm.pts2)
            good = keep & (err0 < GT_PX)
            n = int(good.sum())
            label = f"{seq} 1-{Path(pair.label.split('-')[-1]).stem[3:]}"
            if n == 0:
                print(f"{label:12s} {n:5d}")
                continue
            p1, p2 = fm.pts1[good], fm.pts2[good]
            if args.homographies == "gt":
                homs = np.tile(np.stack([np.eye(3), np.linalg.inv(pair.H_2from1)]), (n, 1, 1, 1))
            else:
                homs = fr.patch_homographies[fr.labels[good]]
            med0 = float(np.median(err0[good]))
            med, extra = {}, ""
            for name, cfg in cfgs.items():
                r = refine_pair(img1, img2, p1, p2, homs, config=cfg)
                med[name] = float(np.median(transfer_error(pair.H_2from1, r.pts1, r.pts2)))
                if name == "lsm":
                    extra = f"{r.stats.get('lsm_applied', 0)}/{r.stats['moved']}"
            row = (f"{label:12s} {n:5d} {med0:7.3f} {med['ncc']:7.3f} {med['lsm']:7.3f} "
                   f"{med['ncc'] / med0:8.3f} {med['lsm'] / med0:8.3f} {med['lsm'] / med['ncc']:8.3f} "
                   f"{extra}" + "".join(f" {med[name] / med0:10.3f}" for name in extra_names))
            print(row + ("" if n >= args.min_matches else "  (too few: not counted)"))
            if n >= args.min_matches:
                for name in ratios:
                    ratios[name].append(med[name] / med0)
                    worse[name] += int(med[name] > med0)
    for name in ratios:
        if ratios[name]:
            print(f"{name}: median after/before {np.median(ratios[name]):.3f} over "
                  f"{len(ratios[name])} pairs with >= {args.min_matches} matches; worse on {worse[name]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
