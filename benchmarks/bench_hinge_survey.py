"""The match check on surveys with a planted hinge (:mod:`miho_bench.hinge_scene`), with and
without the hinge search: the correct and wrong matches removed, what the search found.

Wrong pairs agreeing with one another on the second half turned by ``--turn`` degrees, planted
at ``--ratios`` wrong pairs per correct pair across the halves; pycolmap's global mapper as the
estimate (one thread, seed 0), ``--seeds`` scenes each.

    python benchmarks/bench_hinge_survey.py [--ratios 0.3 1 2 4] [--seeds 0 1 2] [--turn 40]
        [--repeated-share 0.6] [--images 24]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from miho_bench.hinge_scene import make_hinged_survey  # noqa: E402
from miho_bench.variants import variant  # noqa: E402


def judge(scene, hinges: bool):
    """The check's decision and the shares of correct / wrong matches it removed."""
    from colmap_miho.adapters.database import ColmapDatabase
    from colmap_miho.sfm.global_estimate import GlobalEstimator
    from colmap_miho.verification import MatchCheckConfig, judge_in_rounds

    cfg = variant(MatchCheckConfig(mode="remove"), look_for_hinges=hinges)
    with ColmapDatabase(scene.database) as db:
        d = judge_in_rounds(scene.matches, GlobalEstimator(src=db, config=cfg, num_threads=1), cfg)
    pairs = sorted(scene.matches)
    ok = np.concatenate([scene.correct[p] for p in pairs])
    failed = np.concatenate([d.failed.get(p, np.zeros(len(scene.matches[p]), bool)) for p in pairs])
    return d, 100 * float(failed[ok].mean()), 100 * float(failed[~ok].mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.3, 1.0, 2.0, 4.0])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--turn", type=float, default=40.0)
    ap.add_argument("--repeated-share", type=float, default=0.6)
    ap.add_argument("--images", type=int, default=24)
    args = ap.parse_args(argv)
    print("| wrong:right | seed | wrong / correct pairs across (median matches) | without the search: correct / wrong "
          "removed | with it: correct / wrong removed | what the search found |")
    print("|---|---:|---|---|---|---|")
    for ratio in args.ratios:
        for seed in args.seeds:
            with tempfile.TemporaryDirectory(prefix="bench-hinge-survey-") as tmp:
                sc = make_hinged_survey(tmp, num_images=args.images, wrong_per_right=ratio, turn_deg=args.turn,
                                        repeated_share=args.repeated_share, seed=seed)
                _, c_off, w_off = judge(sc, False)
                d, c_on, w_on = judge(sc, True)
            wrong_n = np.median([len(sc.matches[p]) for p in sc.wrong_pairs]) if sc.wrong_pairs else 0
            right_n = np.median([len(sc.matches[p]) for p in sc.correct_cross])
            found = "; ".join(f"{h.hinge.angle_deg:.0f} deg, {h.verdict}: {h.action}" for h in d.hinges) or "nothing"
            print(f"| {ratio:g}:1 | {seed} | {len(sc.wrong_pairs)} ({wrong_n:.0f}) / {len(sc.correct_cross)} "
                  f"({right_n:.0f}) | {c_off:.2f}% / {w_off:.1f}% | {c_on:.2f}% / {w_on:.1f}% | {found} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
