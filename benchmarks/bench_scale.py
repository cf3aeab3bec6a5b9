"""How `colmap-miho refine` grows with the scene: time, memory, image reads, walk depth.

Synthetic aerial surveys (``miho_bench.synthetic.make_survey_scene``: serpentine
flight lines, a point seen by the few images around it, pairs = next ``--sequential`` images
plus ``--nearest`` nearest camera centres, images rendered by ``pycolmap.synthesize_images``)
at ``--sizes`` images, and the real scenes of ``../shared/data`` (``--scenes``, pycolmap SIFT +
exhaustive matching, ``--max-features`` per image). For each scene ``colmap-miho refine`` runs
in a child process (``--workers``) and the script records:

- seconds per stage from the refine JSON summary (``seconds``), and the child's wall time;
- peak RSS: ``rss_tree_mb`` = peak of the summed RSS of the refine process and all its
  descendants (worker processes included), sampled by psutil every ``--poll`` seconds (a
  lower bound); ``hwm_max_mb`` = the largest single process's peak RSS (the kernel's VmHWM of
  each process, read at every sample); ``hwm_sum_mb`` = the sum of those per-process peaks (an
  upper bound of the tree's peak). Not ``ru_maxrss``: Linux carries the launching process's
  RSS at fork through ``exec`` into the child's ``ru_maxrss``, so it reads this script's own
  size (1.1 GB after a SIFT run) instead of refine's;
- pairs, matches in, images, images loaded / decoded, walk levels (``n/a`` when the summary
  has no such key);
- pycolmap SIFT extraction + exhaustive matching seconds on the same images with the same
  thread count (cached with the scene: ``sift.json``), and refine / (extraction + matching).
  A synthetic scene of more than ``--sift-sample`` images is timed on that many random images
  and scaled (per image, per pair: exhaustive matching is quadratic, 400 images are 79,800
  pairs); such figures carry a ``~`` in the table.

Then a log-log least-squares fit of refine seconds and of peak RSS against matches over the
synthetic sizes (exponent = slope), a table (``scale.md``), all figures (``scale.json``) and a
plot (``scale.png``) in ``--out``. Scenes are cached under ``--work``; the refined database is
rewritten on every run.

With ``--calibrated`` the scenes are the realistic surveys of
``miho_bench.calibrated_survey.make_calibrated_survey`` instead (calibrated camera, CALIBRATED
two-view geometries with E and F, 8,000-28,000 match ends per image with wrong and
repeated-structure matches), one per size and pair graph of ``--graphs``; the table
(``--name``.md / .json) then splits the match check (its global mapper, the pairs' own
rotations), gives its share of ``refine``, the outcome against the ground truth (true / wrong
verified matches removed) and the check's verdicts, and fits each stage per pair graph.

    python benchmarks/bench_scale.py --sizes 25 50 100 200 400 --workers 2
    python benchmarks/bench_scale.py --calibrated --sizes 100 200 400 --graphs sequential retrieval --no-sift \
        --name scale_calibrated
    python benchmarks/bench_scale.py --sizes --scenes middlebury_temple_sparse_ring strecha_fountain_p11
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SIZES = (25, 50, 100, 200, 400)
SCENES = ("middlebury_temple_sparse_ring", "strecha_fountain_p11", "strecha_entry_p10")
NA = "n/a"


# ------------------------------------------------------------------------------ measuring
@dataclass
class ChildRun:
    """One measured child process.

    Attributes:
        returncode: exit status.
        wall_s: wall time from start to exit, seconds.
        rss_tree_mb: peak of the summed RSS of the child and its descendants (psutil samples),
            MiB; a lower bound (a peak between two samples is missed).
        hwm_max_mb: the largest peak RSS (``VmHWM``, kernel-kept) of one process of the tree,
            MiB (0 where ``/proc`` is missing).
        hwm_sum_mb: the sum of the per-process peaks, MiB: an upper bound of the tree's peak.
        samples: number of psutil samples taken.
        stderr_tail: the end of the child's stderr.
        cpu_s: user + system CPU seconds of the child and the descendants it waited for
            (``wait4``'s rusage): less sensitive than ``wall_s`` to other load on the machine.
        loadavg: the machine's 1-minute load average when the child ended.
        cpu_series: (seconds since the start, CPU seconds of the tree so far: every process's
            sampled user + system time, workers included) at every sample.
        client_rss: (seconds since the start, the child's own RSS in MiB) at every sample.
    """

    returncode: int
    wall_s: float
    rss_tree_mb: float
    hwm_max_mb: float
    hwm_sum_mb: float
    samples: int
    stderr_tail: str = ""
    cpu_s: float = 0.0
    loadavg: float = 0.0
    cpu_series: list = field(default_factory=list)
    client_rss: list = field(default_factory=list)


def _vm_hwm(pid: int) -> int:
    """Peak RSS (``VmHWM``) of process ``pid`` in bytes, 0 when unreadable."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _sample_tree(proc, hwm: dict[int, int], cpu: dict[int, float] | None = None) -> int:
    """Summed RSS in bytes of ``proc`` (a psutil.Process) and its living descendants; updates
    ``hwm`` (pid -> largest VmHWM seen) and ``cpu`` (pid -> user + system CPU seconds so far,
    threads included; a process that ended keeps its last sample)."""
    import psutil

    total = 0
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return 0
    for p in procs:
        try:
            total += p.memory_info().rss
            if cpu is not None:
                t = p.cpu_times()
                cpu[p.pid] = max(cpu.get(p.pid, 0.0), t.user + t.system)
        except psutil.Error:
            continue
        hwm[p.pid] = max(hwm.get(p.pid, 0), _vm_hwm(p.pid))
    return total


def stage_windows(wall_s: float, seconds: dict) -> dict[str, tuple[float, float]]:
    """Each stage's (start, end) in seconds since the child started: ``seconds`` = the summary's
    stage wall times in the order they ran, ``total`` last (the run's timer ends when the child
    exits, give or take writing the summary)."""
    edge = wall_s - float(seconds["total"])
    out = {}
    for name, sec in seconds.items():
        if name != "total":
            out[name] = (edge, edge + float(sec))
            edge += float(sec)
    return out


def stage_peaks(series: list[tuple[float, float]], wall_s: float, seconds: dict) -> dict[str, float]:
    """The largest sampled value of ``series`` ((seconds since the start, value) pairs) in each
    stage (:func:`stage_windows`); a stage without a sample is left out; {} without samples."""
    if not series or not seconds.get("total"):
        return {}
    t, v = np.array(series, float).T
    out = {}
    for name, (lo, hi) in stage_windows(wall_s, seconds).items():
        inside = (t >= lo) & (t <= hi)
        if inside.any():
            out[name] = round(float(v[inside].max()), 1)
    return out


def stage_cpu_seconds(series: list[tuple[float, float]], wall_s: float, seconds: dict) -> dict[str, float]:
    """CPU seconds of the whole process tree during each stage of a refine run: ``series`` =
    (seconds since the child started, the tree's CPU seconds so far) samples, ``seconds`` = the
    summary's stage wall times in the order they ran, ``total`` last (the run's timer ends when
    the child exits, give or take writing the summary). {} without samples."""
    if len(series) < 2 or not seconds.get("total"):
        return {}
    t, c = np.array(series, float).T
    start = wall_s - float(seconds["total"])
    out = {name: round(float(np.interp(hi, t, c) - np.interp(lo, t, c)), 2)
           for name, (lo, hi) in stage_windows(wall_s, seconds).items()}
    out["total"] = round(float(np.interp(wall_s, t, c) - np.interp(start, t, c)), 2)
    return out


def run_measured(cmd: list[str], *, env: dict | None = None, poll: float = 0.05,
                 timeout: float | None = None) -> ChildRun:
    """Run ``cmd`` and measure its wall time and peak memory (see :class:`ChildRun`)."""
    import psutil

    t0 = time.perf_counter()
    with open(os.devnull, "w") as devnull, subprocess.Popen(cmd, env=env, stdout=devnull,
                                                            stderr=subprocess.PIPE) as child:
        peak, samples, done = 0, 0, threading.Event()
        hwm: dict[int, int] = {}
        stderr_chunks: list[bytes] = []

        cpu: dict[int, float] = {}
        series: list[tuple[float, float]] = []
        client: list[tuple[float, float]] = []

        def sample() -> None:
            nonlocal peak, samples
            try:
                proc = psutil.Process(child.pid)
            except psutil.Error:
                return
            while not done.is_set():
                peak = max(peak, _sample_tree(proc, hwm, cpu))
                now = time.perf_counter() - t0
                series.append((now, sum(cpu.values())))
                with contextlib.suppress(psutil.Error):
                    client.append((now, proc.memory_info().rss / 2**20))
                samples += 1
                done.wait(poll)

        def drain() -> None:
            assert child.stderr is not None
            for chunk in iter(lambda: child.stderr.read(65536), b""):  # type: ignore[union-attr]
                stderr_chunks.append(chunk)
                del stderr_chunks[:-4]

        threads = [threading.Thread(target=sample, daemon=True), threading.Thread(target=drain, daemon=True)]
        for t in threads:
            t.start()
        deadline = None if timeout is None else t0 + timeout
        while True:
            pid, status, usage = os.wait4(child.pid, os.WNOHANG)
            if pid:
                break
            if deadline is not None and time.perf_counter() > deadline:
                child.kill()
            time.sleep(0.02)
        wall = time.perf_counter() - t0
        child.returncode = os.waitstatus_to_exitcode(status)
        done.set()
        for t in threads:
            t.join(timeout=5)
    tail = b"".join(stderr_chunks).decode(errors="replace")[-2000:]
    return ChildRun(child.returncode, wall, peak / 2**20, max(hwm.values(), default=0) / 2**20,
                    sum(hwm.values()) / 2**20, samples, tail, usage.ru_utime + usage.ru_stime, os.getloadavg()[0],
                    series, client)


def fit_power_law(x, y) -> tuple[float, float]:
    """Least-squares fit of log(y) = a + b log(x); returns (exponent b, prefactor e^a).
    Needs two or more distinct positive x with positive y."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = (x > 0) & (y > 0)
    if ok.sum() < 2 or np.unique(x[ok]).size < 2:
        raise ValueError("a power-law fit needs two or more distinct positive points")
    b, a = np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)
    return float(b), float(math.exp(a))


# --------------------------------------------------------------------------------- scenes
@dataclass
class Scene:
    """A scene to refine: its database, image folder and feature-extraction times."""

    name: str
    kind: str  # "synthetic" or "real"
    database: Path
    images: Path
    work: Path
    sift: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


def synthetic_scene(work: Path, num_images: int, *, seed: int, sequential: int, nearest: int,
                    points_per_image: int) -> Scene:
    """The cached survey scene of ``num_images`` images (built on first use)."""
    from miho_bench.synthetic import make_survey_scene

    params = {"num_images": num_images, "seed": seed, "sequential": sequential, "nearest": nearest,
              "points_per_image": points_per_image}
    tag = f"survey_n{num_images}_s{seed}_q{sequential}_k{nearest}_p{points_per_image}"
    root = work / "synthetic" / tag
    meta = root / "scene.json"
    if not meta.is_file():
        if root.exists():
            import shutil

            shutil.rmtree(root)
        t0 = time.perf_counter()
        sc = make_survey_scene(root, num_images=num_images, points_per_image=points_per_image,
                               sequential=sequential, nearest=nearest, seed=seed)
        tl = [p.track.length() for p in sc.gt_reconstruction.points3D.values()]
        info = {**params, "pairs": len(sc.pairs), "points3D": len(tl), "mean_track_length": float(np.mean(tl)),
                "max_track_length": int(np.max(tl)), "build_s": round(time.perf_counter() - t0, 2)}
        meta.write_text(json.dumps(info, indent=2))
    info = json.loads(meta.read_text())
    return Scene(f"survey{num_images}", "synthetic", root / "database.db", root / "images", root, info=info)


def calibrated_scene(work: Path, num_images: int, *, graph: str, seed: int) -> Scene:
    """The cached calibrated survey (``miho_bench.calibrated_survey.make_calibrated_survey``,
    its defaults) of ``num_images`` images and pair graph ``graph`` (built on first use); the
    ground truth's 3D point per keypoint is kept in ``point3D_ids.npz`` for :func:`outcome`."""
    from miho_bench.calibrated_survey import make_calibrated_survey

    tag = f"calibrated_n{num_images}_{graph}_s{seed}"
    root = work / "calibrated" / tag
    meta = root / "scene.json"
    if not meta.is_file():
        if root.exists():
            import shutil

            shutil.rmtree(root)
        t0 = time.perf_counter()
        sc = make_calibrated_survey(root, num_images=num_images, graph=graph, seed=seed)
        np.savez(root / "point3D_ids.npz", **{str(k): v for k, v in sc.point3D_ids.items()})
        tl = [p.track.length() for p in sc.gt_reconstruction.points3D.values()]
        info = {"num_images": num_images, "graph": graph, "seed": seed, "pairs": len(sc.pairs),
                "candidate_pairs": len(sc.candidate_pairs or []), "loop_pairs": len(sc.loop_pairs or []),
                "points3D": len(tl), "mean_track_length": float(np.mean(tl)), "max_track_length": int(np.max(tl)),
                "build_s": round(time.perf_counter() - t0, 2)}
        meta.write_text(json.dumps(info, indent=2))
    info = json.loads(meta.read_text())
    return Scene(f"{graph[:3]}{num_images}", "synthetic", root / "database.db", root / "images", root, info=info)


#: bounds of the pair-size classes (verified matches of a pair in the input) of the outcome
PAIR_SIZE_BOUNDS = (300, 600, 1000, 1500)


def pair_size_class(n: int) -> str:
    """The pair-size class of a pair of ``n`` verified matches, e.g. ``"300-599"`` or ``"1500+"``."""
    lo = 0
    for hi in PAIR_SIZE_BOUNDS:
        if n < hi:
            return f"{lo}-{hi - 1}"
        lo = hi
    return f"{lo}+"


def outcome(scene: Scene, refined: Path) -> dict:
    """The refine output against the ground truth (a calibrated survey's ``point3D_ids.npz``):
    verified matches in and out that join two observations of one 3D point (correct) or not
    (wrong), the shares of each removed (%), match ends per image in (median, min, max), and the
    wrong matches in and removed per pair-size class (:func:`pair_size_class`: a larger survey
    holds another mix of pairs, and the filter removes a smaller share in larger pairs); {} for
    a scene without ground truth."""
    from colmap_miho.adapters.database import ColmapDatabase

    gt = scene.work / "point3D_ids.npz"
    if not gt.is_file():
        return {}
    ids = {int(k): v for k, v in np.load(gt).items()}

    def read(path: Path) -> dict[tuple[int, int], np.ndarray]:
        with ColmapDatabase(path) as db:
            return {(p.image_id1, p.image_id2): db.matches(p.image_id1, p.image_id2, "verified").astype(np.int64)
                    for p in db.pairs("verified")}

    def wrong(p: tuple[int, int], m: np.ndarray) -> np.ndarray:
        a, b = ids[p[0]][m[:, 0]], ids[p[1]][m[:, 1]]
        return ~((a >= 0) & (a == b))

    before, after = read(scene.database), read(refined)
    ends = np.zeros(len(ids) + 1, np.int64)
    c_in = w_in = c_out = w_out = 0
    by_size: dict[str, list[int]] = {}
    for p, m in before.items():
        bad = wrong(p, m)
        kept = after.get(p, np.zeros((0, 2), np.int64))
        bad_kept = wrong(p, kept) if len(kept) else np.zeros(0, bool)
        c_in, w_in = c_in + int((~bad).sum()), w_in + int(bad.sum())
        c_out, w_out = c_out + int((~bad_kept).sum()), w_out + int(bad_kept.sum())
        cls = by_size.setdefault(pair_size_class(len(m)), [0, 0, 0])
        cls[0], cls[1], cls[2] = cls[0] + 1, cls[1] + int(bad.sum()), cls[2] + int(bad.sum()) - int(bad_kept.sum())
        ends[p[0]] += len(m)
        ends[p[1]] += len(m)
    ends = ends[1:]
    return {"correct_in": c_in, "wrong_in": w_in, "correct_out": c_out, "wrong_out": w_out,
            "correct_removed_pct": round(100 * (c_in - c_out) / max(c_in, 1), 3),
            "wrong_removed_pct": round(100 * (w_in - w_out) / max(w_in, 1), 2),
            "ends_per_image": [int(np.median(ends)), int(ends.min()), int(ends.max())],
            "wrong_by_pair_size": {k: {"pairs": v[0], "wrong_in": v[1], "wrong_removed": v[2]}
                                   for k, v in sorted(by_size.items(), key=lambda kv: _class_start(kv[0]))}}


def _class_start(cls: str) -> int:
    """The smallest match count of a :func:`pair_size_class` name."""
    return int(cls.split("-")[0].rstrip("+"))


def real_scene(data: Path, work: Path, name: str) -> Scene | None:
    """A real scene of ``data`` with its SIFT database (extracted on first use; see
    :func:`sift_times`), or None when its images are missing."""
    root = data / name
    if not (root / "images").is_dir():
        print(f"skip {name}: no images at {root / 'images'}", file=sys.stderr)
        return None
    w = work / "real" / name
    return Scene(name, "real", w / "sift.db", root / "images", w)


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")


def sift_times(scene: Scene, *, threads: int, max_features: int, sample_images: int | None = None,
               seed: int = 0) -> dict:
    """pycolmap SIFT extraction + exhaustive matching times of the scene's images (CPU,
    ``threads`` threads, one SIMPLE_RADIAL camera, as ``colmap_miho.sfm.extraction.extract_and_match``)
    into ``work/sift.db``; cached in ``work/sift.json``.

    With more than ``sample_images`` images only a random subset of that many is extracted and
    matched exhaustively, and the times are scaled to the whole scene: extraction by
    N / S images, matching by N (N - 1) / (S (S - 1)) pairs (``estimated``: true). Both are
    per-image and per-pair costs on statistically alike images (the synthetic surveys);
    a real scene is always run whole (its database is refine's input).
    """
    import pycolmap

    from colmap_miho.sfm import colmap_log_to_file

    meta = scene.work / "sift.json"
    key = {"threads": threads, "max_features": max_features, "sample_images": sample_images, "seed": seed}
    if meta.is_file():
        old = json.loads(meta.read_text())
        if all(old.get(k) == v for k, v in key.items()):
            return old
    names = sorted(p.name for p in scene.images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    n = len(names)
    if n < 2:
        raise RuntimeError(f"{scene.images}: {n} image(s), need at least 2")
    subset = names
    if sample_images is not None and n > sample_images:
        rng = np.random.default_rng(seed)
        subset = sorted(rng.choice(names, size=sample_images, replace=False).tolist())
    scene.work.mkdir(parents=True, exist_ok=True)
    db = scene.work / "sift.db"
    db.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = int(max_features)
    extraction.num_threads = int(threads)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = int(threads)
    with colmap_log_to_file(scene.work):
        t0 = time.perf_counter()
        pycolmap.extract_features(str(db), str(scene.images), image_names=subset if subset is not names else [],
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        t1 = time.perf_counter()
        pycolmap.match_exhaustive(str(db), matching_options=matching, device=pycolmap.Device.cpu)
        t2 = time.perf_counter()
    from colmap_miho.adapters.database import ColmapDatabase

    with ColmapDatabase(db) as handle:
        pairs, matches = handle.num_verified_pairs(), handle.num_inlier_matches()
    s = len(subset)
    scale_pairs = n * (n - 1) / (s * (s - 1))
    out = {**key, "num_images": n, "images_run": s, "estimated": s < n,
           "seconds_extract": round((t1 - t0) * n / s, 2), "seconds_match": round((t2 - t1) * scale_pairs, 2),
           "seconds_extract_run": round(t1 - t0, 2), "seconds_match_run": round(t2 - t1, 2),
           "verified_pairs_run": pairs, "inlier_matches_run": matches}
    meta.write_text(json.dumps(out, indent=2))
    return out


# --------------------------------------------------------------------------------- refine
def refine_command(scene: Scene, out_db: Path, json_path: Path, *, workers: int, extra: list[str]) -> list[str]:
    """The ``colmap-miho refine`` command line for ``scene`` (this checkout's code; ``--restart``:
    every run measures the whole job, even after a killed one left its work)."""
    return [sys.executable, "-m", "colmap_miho.cli", "refine", "--database", str(scene.database),
            "--images", str(scene.images), "--output", str(out_db), "--overwrite", "--restart",
            "--workers", str(workers),
            "--json", str(json_path), "-q", *extra]


def _get(summary: dict, key: str):
    """``summary[key]`` or ``summary["refine_stats"][key]``, None when absent."""
    if key in summary:
        return summary[key]
    return summary.get("refine_stats", {}).get(key)


def measure_refine(scene: Scene, *, workers: int, extra: list[str], poll: float, timeout: float | None) -> dict:
    """Run refine on ``scene`` in a child process; returns one row of figures."""
    out_db = scene.work / "refined.db"
    json_path = scene.work / "refine.json"
    json_path.unlink(missing_ok=True)
    path = [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path)}
    run = run_measured(refine_command(scene, out_db, json_path, workers=workers, extra=extra),
                       env=env, poll=poll, timeout=timeout)
    if run.returncode != 0 or not json_path.is_file():
        raise RuntimeError(f"refine failed on {scene.name} (exit {run.returncode}): {run.stderr_tail.strip()[-500:]}")
    summary = json.loads(json_path.read_text())
    secs = summary.get("seconds", {})
    row = {
        "scene": scene.name, "kind": scene.kind, "workers": workers,
        "images": summary.get("num_images"), "pairs": summary.get("num_pairs"),
        "matches": summary.get("matches_in"), "matches_kept": summary.get("matches_kept"),
        "images_loaded": _get(summary, "images_loaded"), "image_decodes": _get(summary, "image_decodes"),
        "decodes_max": summary.get("image_decodes_max"),
        "levels": _get(summary, "levels"), "refine_s": secs.get("total"), "child_wall_s": round(run.wall_s, 2),
        "seconds": secs, "rss_tree_mb": round(run.rss_tree_mb, 1), "hwm_max_mb": round(run.hwm_max_mb, 1),
        "hwm_sum_mb": round(run.hwm_sum_mb, 1),
        "mc_peak_mb": (summary.get("match_check") or {}).get("peak_rss_mb"),
        "rss_samples": run.samples, "scene_info": scene.info,
        "cpu_s": round(run.cpu_s, 1), "loadavg": round(run.loadavg, 2),
        "stage_cpu_s": stage_cpu_seconds(run.cpu_series, run.wall_s, secs),
        "client_peak_mb": stage_peaks(run.client_rss, run.wall_s, secs),
    }
    mc = summary.get("match_check") or {}
    if mc:
        rounds = mc.get("round_seconds") or []
        steps = mc.get("mapper_steps") or []
        row["check"] = {
            "used": mc.get("used"), "reason": mc.get("reason"), "rounds": mc.get("rounds"),
            "registered": mc.get("images_registered"), "untrusted": len(mc.get("images_untrusted") or []),
            "cut_off": len(mc.get("images_cut_off") or []), "matches_judged": mc.get("matches_judged"),
            "matches_removed": mc.get("matches_removed"), "pairs_removed": mc.get("pairs_removed"),
            "hinges": len(mc.get("hinges") or []),
            "parts_s": {k: round(sum(r.get(k, 0.0) for r in rounds), 2)
                        for k in sorted({k for r in rounds for k in r})},
            "mapper_steps_s": {k: round(sum(r.get(k, 0.0) for r in steps), 2)
                               for k in sorted({k for r in steps for k in r})},
        }
    if secs.get("total") and secs.get("match_check") is not None:
        row["check_share"] = round(secs["match_check"] / secs["total"], 3)
    row.update(outcome(scene, out_db))
    sift = scene.sift
    if sift:
        fm = sift["seconds_extract"] + sift["seconds_match"]
        row.update(sift_extract_s=sift["seconds_extract"], sift_match_s=sift["seconds_match"],
                   sift_total_s=round(fm, 2), sift_estimated=bool(sift.get("estimated")),
                   sift_images_run=sift.get("images_run"))
        if row["refine_s"] and fm > 0:
            row["ratio"] = round(row["refine_s"] / fm, 3)
    return row


# -------------------------------------------------------------------------------- reports
COLUMNS = ("scene", "images", "pairs", "matches", "refine_s", "read", "filter", "match_check", "refine", "write",
           "mc_peak_mb", "rss_tree_mb", "hwm_max_mb", "hwm_sum_mb", "images_loaded", "image_decodes", "decodes_max",
           "levels", "sift_total_s", "ratio", "sift_graph_s", "ratio_graph")


def fmt(v) -> str:
    """A table cell: ``n/a`` for None, floats with 2 decimals (1 above 100)."""
    if v is None:
        return NA
    if isinstance(v, float):
        return f"{v:.1f}" if abs(v) >= 100 else f"{v:.2f}"
    return str(v)


FIT_KEYS = ("refine_s", "filter", "match_check", "refine", "rss_tree_mb", "hwm_max_mb", "mc_peak_mb")


def _value(row: dict, key: str):
    """A row's figure: its own key, else a stage's seconds, else a derived ratio."""
    if key in row:
        return row[key]
    if key in row.get("seconds", {}):
        return row["seconds"][key]
    return derived(row).get(key)


def derived(row: dict) -> dict:
    """``sift_graph_s``: SIFT extraction + matching of only refine's pairs (the exhaustive
    per-pair cost times refine's pair count: what a sequential / spatial matcher choosing the
    same graph would spend), and ``ratio_graph`` = refine_s / sift_graph_s; {} without SIFT
    figures."""
    n, pairs = row.get("images"), row.get("pairs")
    if not (row.get("sift_match_s") and n and n > 1 and pairs and row.get("refine_s")):
        return {}
    graph = row["sift_extract_s"] + row["sift_match_s"] / (n * (n - 1) / 2) * pairs
    return {"sift_graph_s": round(graph, 2), "ratio_graph": round(row["refine_s"] / graph, 3)}


def table(rows: list[dict]) -> str:
    """A markdown table of the rows (stage seconds from the refine summary)."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        cells = [fmt(_value(r, c)) for c in COLUMNS]
        if r.get("sift_estimated"):  # scaled from a sample of images (see sift_times)
            for c in ("sift_total_s", "ratio", "sift_graph_s", "ratio_graph"):
                cells[COLUMNS.index(c)] = "~" + cells[COLUMNS.index(c)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def fits(rows: list[dict]) -> dict:
    """Exponents of refine seconds (total, filter and refine stages) and of peak RSS (tree,
    single process) against matches over the synthetic rows; {} with fewer than two sizes."""
    syn = [r for r in rows if r["kind"] == "synthetic" and r.get("matches")]
    if len({r["matches"] for r in syn}) < 2:
        return {}
    m = [r["matches"] for r in syn]
    out = {}
    for key in FIT_KEYS:
        y = [_value(r, key) or 0 for r in syn]
        if sum(v > 0 for v in y) >= 2:
            b, c = fit_power_law(m, y)
            out[key] = {"exponent": round(b, 3), "prefactor": c}
    return out


CHECK_COLUMNS = ("scene", "images", "pairs", "loops", "matches", "ends/img", "refine_s", "read", "filter",
                 "match_check", "mapper", "pair_rot", "refine", "write", "check_share", "rss_tree_mb", "hwm_max_mb",
                 "correct_rm_%", "wrong_rm_%", "check_rm", "pairs_rm", "trusted", "rounds", "loadavg",
                 "cpu:total", "cpu:filter", "cpu:match_check", "cpu:refine", "cpu_check_share",
                 "mem:read", "mem:filter", "mem:match_check", "mem:refine", "mem:write")
CHECK_FIT_KEYS = ("refine_s", "read", "filter", "match_check", "mapper", "pair_rotations", "refine", "write",
                  "rss_tree_mb", "hwm_max_mb", "cpu:total", "cpu:filter", "cpu:match_check", "cpu:refine")


def check_value(row: dict, key: str):
    """A figure of a calibrated-survey row: the match check's parts ("mapper", "pair_rotations",
    the mapper's steps) as well as :func:`_value`'s."""
    check = row.get("check") or {}
    cpu = row.get("stage_cpu_s") or {}
    if key.startswith("cpu:"):
        return cpu.get(key[4:])
    if key.startswith("mem:"):
        return (row.get("client_peak_mb") or {}).get(key[4:])
    if key == "cpu_check_share":
        return round(cpu["match_check"] / cpu["total"], 3) if cpu.get("total") and "match_check" in cpu else None
    if key in check.get("parts_s", {}):
        return check["parts_s"][key]
    if key in check.get("mapper_steps_s", {}):
        return check["mapper_steps_s"][key]
    return _value(row, key)


def check_table(rows: list[dict]) -> str:
    """The calibrated surveys' table: stage seconds, the check's share of ``refine`` and its
    mapper / pairs' rotations, peak memory, the outcome against the ground truth and the check's
    verdicts."""
    lines = ["| " + " | ".join(CHECK_COLUMNS) + " |", "|" + "---|" * len(CHECK_COLUMNS)]
    for r in rows:
        c = r.get("check") or {}
        e = r.get("ends_per_image") or [None] * 3
        cells = {"loops": (r.get("scene_info") or {}).get("loop_pairs"),
                 "ends/img": f"{e[0]} ({e[1]}-{e[2]})" if e[0] is not None else None,
                 "mapper": check_value(r, "mapper"), "pair_rot": check_value(r, "pair_rotations"),
                 "correct_rm_%": r.get("correct_removed_pct"), "wrong_rm_%": r.get("wrong_removed_pct"),
                 "check_rm": c.get("matches_removed"), "pairs_rm": c.get("pairs_removed"),
                 "trusted": (f"{c['registered'] - c['untrusted']}/{r.get('images')}" if c.get("registered") is not None
                             else None),
                 "rounds": c.get("rounds")}
        values = (cells[k] if k in cells else check_value(r, k) for k in CHECK_COLUMNS)
        lines.append("| " + " | ".join(fmt(v) for v in values) + " |")
    return "\n".join(lines)


def pair_size_table(rows: list[dict]) -> str:
    """Wrong matches removed per pair-size class (% of the class's wrong matches; pairs and
    wrong matches in brackets) and ``at first mix``: the classes' removal shares weighted by the
    wrong matches per class of the graph's smallest survey (the outcome at a fixed mix of pairs);
    "" without the figures."""
    rs = [r for r in rows if r.get("wrong_by_pair_size")]
    if not rs:
        return ""
    classes = sorted({k for r in rs for k in r["wrong_by_pair_size"]}, key=_class_start)
    first: dict[str, dict] = {}
    for r in sorted(rs, key=lambda r: r.get("images") or 0):
        first.setdefault((r.get("scene_info") or {}).get("graph", ""), r["wrong_by_pair_size"])
    lines = ["| scene | " + " | ".join(f"wrong removed, pairs of {c} matches" for c in classes)
             + " | all | at first mix |", "|---|" + "---:|" * (len(classes) + 2)]
    for r in rs:
        by = r["wrong_by_pair_size"]
        cells = []
        for c in classes:
            v = by.get(c)
            cells.append(f"{100 * v['wrong_removed'] / max(v['wrong_in'], 1):.1f}% ({v['pairs']} / {v['wrong_in']})"
                         if v else "")
        ref = first[(r.get("scene_info") or {}).get("graph", "")]
        weight = {c: ref[c]["wrong_in"] for c in ref if c in by and by[c]["wrong_in"]}
        mixed = sum(weight[c] * by[c]["wrong_removed"] / by[c]["wrong_in"] for c in weight)
        mixed /= max(sum(weight.values()), 1)
        lines.append(f"| {r['scene']} | " + " | ".join(cells)
                     + f" | {fmt(r.get('wrong_removed_pct'))}% | {100 * mixed:.1f}% |")
    return "\n".join(lines)


def check_fits(rows: list[dict]) -> dict:
    """Per pair graph (the scene name's prefix), exponents of :data:`CHECK_FIT_KEYS` against
    matches; a graph with fewer than two sizes is left out."""
    out: dict[str, dict] = {}
    for graph in sorted({(r.get("scene_info") or {}).get("graph", "") for r in rows}):
        rs = [r for r in rows if (r.get("scene_info") or {}).get("graph", "") == graph and r.get("matches")]
        if len({r["matches"] for r in rs}) < 2:
            continue
        m = [r["matches"] for r in rs]
        for key in CHECK_FIT_KEYS:
            y = [check_value(r, key) or 0 for r in rs]
            if sum(v > 0 for v in y) >= 2:
                out.setdefault(graph, {})[key] = round(fit_power_law(m, y)[0], 3)
    return out


def short_name(scene: str) -> str:
    """A plot label: ``survey400`` -> ``400``, ``strecha_fountain_p11`` -> ``fountain``."""
    if scene.startswith("survey"):
        return scene[len("survey"):]
    parts = scene.split("_")
    return parts[1] if len(parts) > 1 else scene


def plot(rows: list[dict], path: Path) -> bool:
    """refine seconds and peak RSS against matches (log-log) with the fitted lines; False
    when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib missing: no plot (pip install 'colmap-miho[plots]')", file=sys.stderr)
        return False
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    syn = [r for r in rows if r["kind"] == "synthetic"]
    real = [r for r in rows if r["kind"] == "real"]
    f = fits(rows)
    for ax, key, label in ((axes[0], "refine_s", "refine seconds"), (axes[1], "rss_tree_mb", "peak RSS, tree (MiB)")):
        for group, marker, name in ((syn, "o", "synthetic survey"), (real, "s", "real (shared/data)")):
            pts = [(r["matches"], r[key]) for r in group if r.get("matches") and r.get(key)]
            if pts:
                x, y = zip(*pts, strict=True)
                ax.loglog(x, y, marker, label=name)
                for r in group:
                    if r.get("matches") and r.get(key):
                        ax.annotate(short_name(r["scene"]), (r["matches"], r[key]), fontsize=7,
                                    xytext=(3, 3), textcoords="offset points")
        if key in f and syn:
            xs = np.geomspace(min(r["matches"] for r in syn), max(r["matches"] for r in syn), 20)
            ax.loglog(xs, f[key]["prefactor"] * xs ** f[key]["exponent"], "--",
                      label=f"fit: exponent {f[key]['exponent']:.2f}")
        if key == "refine_s":
            for key2, marker, name in (("sift_total_s", "x", "SIFT extract + exhaustive match"),
                                       ("sift_graph_s", "+", "SIFT extract + match of refine's pairs")):
                pts = [(r["matches"], _value(r, key2)) for r in rows if r.get("matches") and _value(r, key2)]
                if pts:
                    x, y = zip(*pts, strict=True)
                    ax.loglog(x, y, marker, label=name)
        from matplotlib.ticker import LogLocator, ScalarFormatter

        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(ScalarFormatter())
        ax.yaxis.set_minor_formatter(ScalarFormatter() if key != "refine_s" else plt.NullFormatter())
        ax.xaxis.set_minor_formatter(plt.NullFormatter())
        ax.set_xlabel("matches in")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"colmap-miho refine, {rows[0]['workers']} worker(s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=list(SIZES), help="synthetic scene sizes (images)")
    ap.add_argument("--scenes", nargs="*", default=[], help=f"real scenes of --data ({', '.join(SCENES)})")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_scale"), help="scene cache")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results", help="scale.{md,json,png}")
    ap.add_argument("--workers", type=int, default=2, help="refine --workers and SIFT threads")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sequential", type=int, default=2, help="pairs with the next N images")
    ap.add_argument("--nearest", type=int, default=6, help="pairs with the N nearest camera centres")
    ap.add_argument("--points-per-image", type=int, default=300)
    ap.add_argument("--max-features", type=int, default=4096, help="SIFT features per image")
    ap.add_argument("--no-sift", action="store_true", help="skip SIFT extraction + matching (no ratio)")
    ap.add_argument("--sift-sample", type=int, default=20,
                    help="synthetic scenes with more images: SIFT times scaled from this many random images")
    ap.add_argument("--poll", type=float, default=0.05, help="RSS sampling period, seconds")
    ap.add_argument("--timeout", type=float, default=None, help="kill a refine after this many seconds")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="refine --set KEY=VALUE")
    ap.add_argument("--refine-arg", action="append", default=[], help="extra refine argument (repeatable)")
    ap.add_argument("--calibrated", action="store_true",
                    help="calibrated surveys (miho_bench.calibrated_survey) of --graphs, not make_survey_scene")
    ap.add_argument("--graphs", nargs="+", default=["sequential", "retrieval"],
                    help="--calibrated: pair graphs (exhaustive, sequential, retrieval), each at every size")
    ap.add_argument("--append", action="store_true",
                    help="add the rows to those of --out/NAME.json (a sweep run in parts) instead of replacing them")
    ap.add_argument("--name", default="scale", help="output file stem in --out (NAME.md, NAME.json, NAME.png)")
    ap.add_argument("--note", default="", help="text below the table (e.g. the commands that made its rows)")
    ap.add_argument("--report-only", action="store_true",
                    help="measure nothing: rewrite scale.md and scale.png from --out/scale.json")
    args = ap.parse_args(argv)
    if any(n < 2 for n in args.sizes):
        ap.error("--sizes must be >= 2 images")
    if args.workers < 1:
        ap.error("--workers must be >= 1")
    if args.sift_sample < 2:
        ap.error("--sift-sample must be >= 2 images")
    unknown = [s for s in args.scenes if s not in SCENES and not (args.data / s).is_dir()]
    if unknown:
        ap.error(f"unknown scene(s) {', '.join(unknown)} (not in {args.data})")
    try:
        import psutil  # noqa: F401
    except ImportError:
        ap.error("psutil is needed for the RSS figures (pip install psutil)")

    if args.report_only:
        if not (args.out / f"{args.name}.json").is_file():
            ap.error(f"--report-only: no {args.out / (args.name + '.json')}")
        saved = json.loads((args.out / f"{args.name}.json").read_text())
        args.calibrated = any("check" in r for r in saved["rows"])
        args.workers = saved["workers"]
        args.poll = saved.get("poll", args.poll)
        args.sift_sample = saved.get("sift_sample", args.sift_sample)
        print(write_report(saved["rows"], args, saved.get("refine_args", []), write_json=False,
                           note=args.note or saved.get("note", "")))
        return 0

    import pycolmap

    pycolmap.logging.minloglevel = 2
    extra = [x for o in args.overrides for x in ("--set", o)] + list(args.refine_arg)
    # a Scene, or a function building one; the real scenes first: small, and each is one target of its own
    scenes: list = []
    for name in args.scenes:
        rs = real_scene(args.data, args.work, name)
        if rs is not None:
            scenes.append(rs)
    def build_calibrated(n: int, graph: str) -> Scene:
        t0 = time.perf_counter()
        sc = calibrated_scene(args.work, n, graph=graph, seed=args.seed)
        print(f"{sc.name}: scene ready in {time.perf_counter() - t0:.1f} s ({sc.info['pairs']} pairs, mean track "
              f"{sc.info['mean_track_length']:.2f})", file=sys.stderr)
        return sc

    import functools

    # built when its turn comes: a long sweep measures its small sizes first
    sizes = args.sizes if args.calibrated else ()
    scenes += [functools.partial(build_calibrated, n, g) for n in sizes for g in args.graphs]
    for n in () if args.calibrated else args.sizes:
        t0 = time.perf_counter()
        sc = synthetic_scene(args.work, n, seed=args.seed, sequential=args.sequential, nearest=args.nearest,
                             points_per_image=args.points_per_image)
        print(f"{sc.name}: scene ready in {time.perf_counter() - t0:.1f} s ({sc.info['pairs']} pairs, mean track "
              f"{sc.info['mean_track_length']:.2f}, max {sc.info['max_track_length']})", file=sys.stderr)
        scenes.append(sc)

    rows: list[dict] = []
    if args.append and (args.out / f"{args.name}.json").is_file():  # a long sweep run in parts
        rows = json.loads((args.out / f"{args.name}.json").read_text())["rows"]
    for sc in scenes:
        if not isinstance(sc, Scene):
            sc = sc()
        t0 = time.perf_counter()
        if not args.no_sift or sc.kind == "real":  # a real scene's database is the SIFT one
            sample = args.sift_sample if sc.kind == "synthetic" else None
            sc.sift = sift_times(sc, threads=args.workers, max_features=args.max_features, sample_images=sample,
                                 seed=args.seed)
        t_sift = time.perf_counter() - t0
        row = measure_refine(sc, workers=args.workers, extra=extra, poll=args.poll, timeout=args.timeout)
        rows.append(row)
        print(f"{sc.name}: sift {t_sift:.1f} s (cached: ~0), refine child {row['child_wall_s']:.1f} s, "
              f"{row['matches']} matches, peak RSS {row['rss_tree_mb']:.0f} MiB", file=sys.stderr)
        text = write_report(rows, args, extra, note=args.note)  # after every scene: a sweep cut short keeps its rows
    print(text if rows else "no scene measured")
    return 0


def write_report(rows: list[dict], args, extra: list[str], *, write_json: bool = True, note: str = "") -> str:
    """Write ``scale.md``, ``scale.json`` (unless not ``write_json``) and ``scale.png`` of
    ``rows`` to ``args.out``; returns the markdown (with ``note`` below the table)."""
    if getattr(args, "calibrated", False):
        return write_check_report(rows, args, extra, write_json=write_json, note=note)
    f = fits(rows)
    md = [f"colmap-miho refine, {args.workers} worker(s), refine args: {' '.join(extra) or '-'}; "
          f"refine_s = summary seconds.total, read/filter/refine/write = stage seconds; rss_tree_mb = peak "
          f"summed RSS of refine + workers (psutil, {args.poll} s), hwm_max_mb / hwm_sum_mb = largest / sum of "
          f"the per-process peak RSS (VmHWM); sift_total_s = pycolmap SIFT extraction + exhaustive matching "
          f"({args.workers} threads); "
          f"ratio = refine_s / sift_total_s (~: SIFT times scaled from {args.sift_sample} random images); "
          f"sift_graph_s = SIFT extraction + matching of refine's pairs only (exhaustive per-pair cost x pairs), "
          f"ratio_graph = refine_s / sift_graph_s",
          "", table(rows), ""]
    for key, v in f.items():
        md.append(f"- fit {key} ~ matches^{v['exponent']:.3f} over the synthetic sizes")
    if note:
        md += ["", note]
    text = "\n".join(md)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scale.md").write_text(text + "\n")
    if write_json:
        from bench_known_cameras import portable_argv

        meta = {"argv": portable_argv(sys.argv[1:]), "refine_args": extra, "workers": args.workers, "poll": args.poll,
                "sift_sample": args.sift_sample, "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                "cpu_count": os.cpu_count(), "fits": f, "rows": rows}
        (args.out / "scale.json").write_text(json.dumps(meta, indent=2) + "\n")
    plot(rows, args.out / "scale.png")
    return text

def write_check_report(rows: list[dict], args, extra: list[str], *, write_json: bool = True, note: str = "") -> str:
    """``NAME.md`` / ``NAME.json`` of the calibrated surveys (:func:`check_table`,
    :func:`check_fits`); returns the markdown."""
    f = check_fits(rows)
    md = [f"colmap-miho refine on calibrated surveys, {args.workers} worker(s), refine args: {' '.join(extra) or '-'}; "
          "seconds from the refine summary (mapper / pair_rot: the match check's global mapper and pairs' "
          "own rotations, all rounds); check_share = match_check / refine_s; rss_tree_mb = peak summed RSS of "
          f"refine + workers (psutil, {args.poll} s), hwm_max_mb = largest per-process peak (VmHWM); correct_rm_% / "
          "wrong_rm_% = verified matches in the input that are true / wrong correspondences (ground truth) and are "
          "not in the output; check_rm / pairs_rm = matches / pairs the check removed; trusted = images the check "
          "trusted / images; loadavg = the machine's 1-minute load when refine ended (other jobs share the machine: "
          "wall times are noisy where it exceeds the cores); cpu:STAGE = CPU seconds of refine and its workers "
          "during the stage (psutil samples of the process tree, stages placed by the summary's seconds), "
          "cpu_check_share = cpu:match_check / cpu:total; mem:STAGE = the refine process's own largest sampled RSS "
          "during the stage, MiB (workers not counted)", "",
          check_table(rows), ""]
    sizes = pair_size_table(rows)
    if sizes:
        md += ["Wrong matches removed by pair size (verified matches of the pair in the input; in brackets: pairs / "
               "wrong matches in the class); at first mix = the classes' shares weighted as the graph's smallest "
               "survey holds its wrong matches:", "", sizes, ""]
    for graph, v in f.items():
        md.append(f"- fit ({graph}) exponent vs matches: " + ", ".join(f"{k} {e:.2f}" for k, e in v.items()))
    if note:
        md += ["", note]
    text = "\n".join(md)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(text + "\n")
    if write_json:
        from bench_known_cameras import portable_argv

        meta = {"argv": portable_argv(sys.argv[1:]), "refine_args": extra, "workers": args.workers, "poll": args.poll,
                "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "cpu_count": os.cpu_count(), "fits": f,
                "note": note, "rows": rows}
        (args.out / f"{args.name}.json").write_text(json.dumps(meta, indent=2) + "\n")
    return text


if __name__ == "__main__":
    sys.exit(main())
