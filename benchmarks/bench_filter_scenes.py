"""Where the filter's time goes on the pairs of real COLMAP databases: RANSAC counters and CPU time.

For each scene and matching setting (the databases of ``benchmarks/bench_accuracy.py``, built
and cached the same way under ``--work``: pycolmap SIFT, exhaustive matching; ``permissive`` =
ratio 0.95, no cross-check), the pairs' matches (``--source``, default the verified ones that
``refine`` filters) are read once and cached beside the database, then every variant filters
every pair with the pair's own seed (as ``refine`` does). Per scene, setting and variant:

- ``cpu s``: process CPU seconds of all pairs (the filter is single-threaded numpy), the
  median over ``--repeat`` passes; the variants of one pass run back to back, pair by pair;
- per pair: MOP ``rounds``, minimal samples ``drawn``, ``samples`` (those passing the spread
  test: RANSAC iterations), ``valid`` hypotheses (quasi-affine, reflection check), ``scored``
  (fully scored) hypotheses;
- ``ms/round``: CPU milliseconds per MOP round; ``kept``: matches kept; ``same``: share of
  the matches with the same inlier flag as the first variant.

    python benchmarks/bench_filter_scenes.py [--work /tmp/bench_accuracy] [--settings permissive]
        [--scenes demo strecha_fountain_p11 ...] [--variant NAME:key=value,...] [--repeat 3]

A variant is a name and :class:`~colmap_miho.filtering.config.FilterConfig` overrides
(``name:key=value,key=value``); the first variant is always ``default`` (the recipe's
filter, ``mop_miho`` with paper defaults). The key ``kernels=numpy`` runs a variant on the
numpy reference kernels instead of the compiled ones (:mod:`colmap_miho.filtering.compiled`),
so that both are timed pair by pair in one process. ``--extra NAME=DB`` adds a database of
another layout (e.g. ``bench_scale.py``'s synthetic survey ``.../synthetic/survey_n50_.../
database.db``). The first filter call of the process (numba's import and cache load,
scipy's k-d tree) is timed apart, before the passes, and printed as ``cold start``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from bench_accuracy import DEMO, MAX_FEATURES, SETTINGS, SHARED_SCENES, build_database, scene_inputs
from bench_hard_pairs import parse_variant

from colmap_miho import filter_matches
from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.enums import MatchSource
from colmap_miho.filtering.config import FilterConfig
from colmap_miho.filtering.miho import choose_rotation
from colmap_miho.filtering.scoring import NumpyScoring
from colmap_miho.seeds import pair_seed
from miho_bench.variants import configured

REPO = Path(__file__).resolve().parents[1]
COUNTERS = ("rounds", "drawn", "samples", "valid", "full_scored")


@dataclasses.dataclass(frozen=True)
class Pair:
    pts1: np.ndarray  # (M, 2) pixels, integer = pixel centre
    pts2: np.ndarray
    seed: int


def scene_pairs(db_path: Path, source: str) -> list[Pair]:
    """The pairs of a database as ``refine`` reads them, cached in ``filter_pairs_<source>.npz``."""
    cache = db_path.with_name(f"filter_pairs_{source}.npz")
    if not cache.is_file():
        arrays = {}
        with ColmapDatabase(db_path) as db:
            kps = {im.image_id: db.keypoints(im.image_id) for im in db.images()}
            for k, p in enumerate(db.pairs(source)):
                i, j = p.image_id1, p.image_id2
                m = db.matches(i, j, source)
                arrays[f"p1_{k}"] = kps[i][m[:, 0]]
                arrays[f"p2_{k}"] = kps[j][m[:, 1]]
                arrays[f"seed_{k}"] = np.array(pair_seed(0, i, j), dtype=np.uint64)
        np.savez(cache, **arrays)
    data = np.load(cache)
    n = sum(1 for k in data.files if k.startswith("seed_"))
    return [Pair(data[f"p1_{k}"], data[f"p2_{k}"], int(data[f"seed_{k}"])) for k in range(n)]


def run_pass(pairs: list[Pair], configs: dict[str, FilterConfig],
             numpy_kernels: frozenset[str] = frozenset()) -> dict[str, dict]:
    """One pass of every variant over ``pairs`` (variants back to back on each pair); the
    variants named in ``numpy_kernels`` run on the numpy reference kernels."""
    out = {name: {"cpu": 0.0, "kept": 0, "masks": [], **dict.fromkeys(COUNTERS, 0)} for name in configs}
    for p in pairs:
        for name, cfg in configs.items():
            c0 = time.process_time()
            with numpy_reference(name in numpy_kernels):
                r = filter_matches(p.pts1, p.pts2, config=cfg, seed=p.seed)
            row = out[name]
            row["cpu"] += time.process_time() - c0
            row["kept"] += r.num_inliers
            row["masks"].append(r.inliers)
            for key in COUNTERS:
                row[key] += r.stats.get(key, 0)
    return out


@contextlib.contextmanager
def numpy_reference(on: bool):
    """While ``on``, the filter runs its numpy reference kernels: the defaults of the scoring's
    and the rotation fix's ``compiled`` switched to False (restored after)."""
    saved = NumpyScoring.__init__.__defaults__, dict(choose_rotation.__kwdefaults__)
    if on:
        NumpyScoring.__init__.__defaults__ = (False,)
        choose_rotation.__kwdefaults__["compiled"] = False
    try:
        yield
    finally:
        NumpyScoring.__init__.__defaults__ = saved[0]
        choose_rotation.__kwdefaults__.update(saved[1])


def cold_start() -> float:
    """Process CPU seconds of the first filter call (a small synthetic pair)."""
    rng = np.random.default_rng(0)
    c0 = time.process_time()
    filter_matches(rng.uniform(0, 500, (300, 2)), rng.uniform(0, 500, (300, 2)), seed=0)
    return time.process_time() - c0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_accuracy"),
                    help="cache of scenes and databases (bench_accuracy.py's layout)")
    ap.add_argument("--scenes", nargs="+", default=[DEMO, *SHARED_SCENES])
    ap.add_argument("--settings", nargs="+", default=["permissive"], choices=list(SETTINGS))
    ap.add_argument("--source", default=MatchSource.VERIFIED.value, choices=MatchSource.values())
    ap.add_argument("--max-features", type=int, default=4096)
    ap.add_argument("--variant", action="append", default=[], help="name:key=value,... (repeatable)")
    ap.add_argument("--repeat", type=int, default=1, help="passes; CPU time is their median")
    ap.add_argument("--max-pairs", type=int, default=0, help="first N pairs per scene (0 = all)")
    ap.add_argument("--extra", action="append", default=[], metavar="NAME=DB",
                    help="another database to filter, all its pairs (repeatable)")
    args = ap.parse_args(argv)
    variants = [("default", {})] + [parse_variant(v) for v in args.variant]
    numpy_kernels = frozenset(name for name, over in variants if over.pop("kernels", None) == "numpy")
    configs = {name: configured(FilterConfig, **over) for name, over in variants}
    print(f"cold start: {cold_start():.2f} CPU s (first filter call of the process)")
    print("scene/setting | variant | pairs | matches | cpu s | rounds | drawn | samples | valid | "
          "scored | ms/round | kept | same")
    jobs: list[tuple[str, Path]] = []
    for scene in args.scenes:
        found = scene_inputs(scene, args.data, args.work)
        if found is None:
            print(f"skip {scene}: no data", file=sys.stderr)
            continue
        for setting in args.settings:
            db = build_database(found[0], args.work / scene, setting, MAX_FEATURES.get(scene, args.max_features))
            jobs.append((f"{scene}/{setting}", db))
    jobs += [(name, Path(db)) for name, _, db in (e.partition("=") for e in args.extra)]
    for label, db in jobs:
        pairs = scene_pairs(db, args.source)
        if args.max_pairs:
            pairs = pairs[: args.max_pairs]
        matches = sum(len(p.pts1) for p in pairs)
        passes = [run_pass(pairs, configs, numpy_kernels) for _ in range(args.repeat)]
        first = np.concatenate(passes[0]["default"]["masks"]) if pairs else np.zeros(0, bool)
        for name in configs:
            row = passes[0][name]
            cpu = float(np.median([p[name]["cpu"] for p in passes]))
            n = max(len(pairs), 1)
            mask = np.concatenate(row["masks"]) if pairs else first
            same = float(np.mean(mask == first)) if len(first) else float("nan")
            per = " | ".join(f"{row[k] / n:.1f}" for k in COUNTERS)
            ms = 1000 * cpu / max(row["rounds"], 1)
            print(f"{label} | {name} | {len(pairs)} | {matches} | {cpu:.2f} | {per} | "
                  f"{ms:.1f} | {row['kept']} | {same:.4f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
