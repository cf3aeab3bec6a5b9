"""Tentative matches of GT pairs from the benchmark's front ends, cached on disk.

* ``sift`` / ``gftt``: :func:`miho_bench.frontend.sift_matches`;
* ``colmap``: pycolmap's own SIFT extraction and exhaustive matching of the scene's images
  (CPU), read back from the database through :mod:`colmap_miho.adapters.database` (which converts
  COLMAP's +0.5 pixel convention).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from .benchmark import PairInput
from .datasets import PairGT
from .frontend import sift_matches

log = logging.getLogger(__name__)

FRONTENDS = ("sift", "gftt", "colmap")


def _key(pair: PairGT, frontend: str) -> str:
    return f"{frontend}__{pair.label.replace('/', '__')}".replace(".", "_")


def _colmap_database(image_dir: Path, cache_dir: Path) -> Path:
    """Build (once) a COLMAP database of every image in ``image_dir`` with pycolmap SIFT +
    exhaustive matching on the CPU, single camera."""
    import pycolmap

    name = f"colmap__{image_dir.parent.name}__{image_dir.name}.db"
    db = cache_dir / name
    if db.is_file():
        return db
    tmp = cache_dir / (name + ".tmp")
    tmp.unlink(missing_ok=True)
    work = cache_dir / (name + ".images")
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    for p in sorted(image_dir.iterdir()):  # only the images (Oxford folders also hold H files)
        if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".ppm", ".pgm"):
            (work / p.name).symlink_to(p.resolve())
    pycolmap.extract_features(str(tmp), str(work), camera_mode=pycolmap.CameraMode.SINGLE,
                              device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(str(tmp), device=pycolmap.Device.cpu)
    tmp.rename(db)
    shutil.rmtree(work)
    return db


def _colmap_matches(pair: PairGT, cache_dir: Path):
    from colmap_miho.adapters.database import ColmapDatabase

    db_path = _colmap_database(pair.path1.parent, cache_dir)
    with ColmapDatabase(db_path) as db:
        ids = {r.name: r.image_id for r in db.images()}
        i, j = ids[pair.path1.name], ids[pair.path2.name]
        swap = i > j
        m = db.matches(min(i, j), max(i, j), "raw").astype(np.int64)
        if swap:
            m = m[:, ::-1]
        raw1, raw2 = db.raw_keypoints(i), db.raw_keypoints(j)
        k1, k2 = db.keypoints(i), db.keypoints(j)
        d1 = np.asarray(db.handle.read_descriptors(i).data, np.float32)[m[:, 0]]
        d2 = np.asarray(db.handle.read_descriptors(j).data, np.float32)[m[:, 1]]
    # COLMAP keeps no ratio score: use the descriptor distance (scores must vary, AdaLAM
    # picks seeds as local score optima and exhausts memory on ties).
    scores = np.linalg.norm(d1 - d2, axis=1) / 512.0
    aff = lambda raw, idx: raw[idx, 2:6].reshape(-1, 2, 2).astype(np.float64) if raw.shape[1] == 6 else None  # noqa: E731
    return k1[m[:, 0]], k2[m[:, 1]], scores, aff(raw1, m[:, 0]), aff(raw2, m[:, 1])


def load_inputs(pair: PairGT, frontend: str, cache_dir: Path) -> PairInput:
    """Images and tentative matches of one pair (cached as ``.npz`` in ``cache_dir``)."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    image1, image2 = pair.image1(), pair.image2()
    path = cache_dir / f"{_key(pair, frontend)}.npz"
    if path.is_file():
        d = np.load(path)
        a1 = d["affine1"] if d["affine1"].size else None
        a2 = d["affine2"] if d["affine2"].size else None
        return PairInput(pair, image1, image2, d["pts1"], d["pts2"], d["scores"], a1, a2)
    if frontend in ("sift", "gftt"):
        m = sift_matches(image1, image2, detector=frontend)
        pts1, pts2, scores, a1, a2 = m.pts1, m.pts2, m.scores, m.affine1, m.affine2
    elif frontend == "colmap":
        pts1, pts2, scores, a1, a2 = _colmap_matches(pair, cache_dir)
    else:
        raise ValueError(f"frontend must be one of {', '.join(FRONTENDS)}, got {frontend!r}")
    np.savez(path, pts1=pts1, pts2=pts2, scores=scores,
             affine1=a1 if a1 is not None else np.zeros(0), affine2=a2 if a2 is not None else np.zeros(0))
    return PairInput(pair, image1, image2, pts1, pts2, scores, a1, a2)
