"""The GT oracle filter: every stored match judged by its distance to its GT epipolar line.

What a perfect match filter would give, as a benchmark row beside the real filters. A stored
inlier match whose symmetric GT epipolar distance (see
:func:`~colmap_miho.reporting.track_geometry.symmetric_epipolar_distance`) is above a threshold
(:data:`ORACLE_THRESHOLD_PX`) is a *GT outlier*; the others are *correct* matches.

- :func:`gt_epipolar_distances` (pure): the distance of every stored match of the pairs whose two
  images have GT.
- :func:`outlier_counts` (pure): correct matches, GT outliers and their share, over all pairs and
  over the *correct pairs* (pairs whose median match is within the threshold: a wrong pair's
  matches are all wrong, which says nothing about the matches inside correct pairs).
- :func:`write_oracle_database`: a copy of a database with the GT outliers removed from every
  pair's two-view-geometry inliers, mirrored into its ``matches`` row (as ``refine`` writes
  them); a pair left without matches loses its two-view geometry. Pairs with an image outside
  the GT are left as they are. The input is only read (through a copy).

Pixel convention: integer = pixel centre, for keypoints and GT intrinsics alike.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from colmap_miho.geometry import fundamental_from_poses, symmetric_epipolar_distance
from colmap_miho.reporting.keypoint_accuracy import camera_krt

ORACLE_THRESHOLD_PX = 4.0
"""A match farther than this (px, symmetric) from its GT epipolar line is a GT outlier."""


def pair_distances(cam1, cam2, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """Symmetric GT epipolar distances (M,) px of matched points ``xy1, xy2`` (M, 2) between two
    GT cameras (objects with ``K, R, t``: world-to-camera, pixel-centre K)."""
    F = fundamental_from_poses(*camera_krt(cam1), *camera_krt(cam2))
    return symmetric_epipolar_distance(F, xy1, xy2)


def gt_epipolar_distances(keypoints: Mapping[Hashable, np.ndarray],
                          matches: Mapping[tuple[Hashable, Hashable], np.ndarray],
                          gt: Mapping[Hashable, object]) -> dict[tuple[Hashable, Hashable], np.ndarray]:
    """GT epipolar distance of every match of the pairs whose two images are in ``gt``.

    Args:
        keypoints: image -> float (N, 2) keypoint positions.
        matches: (image a, image b) -> int (M, 2) keypoint indices (column 0 into a).
        gt: image -> camera with ``K, R, t``.

    Returns:
        (a, b) -> float64 (M,) distances in px, in the order of the pair's matches; pairs with an
        image outside ``gt`` are absent.
    """
    out = {}
    for (a, b), m in matches.items():
        if a not in gt or b not in gt:
            continue
        m = np.asarray(m, dtype=np.int64).reshape(-1, 2)
        out[(a, b)] = pair_distances(gt[a], gt[b], np.asarray(keypoints[a])[m[:, 0]],
                                     np.asarray(keypoints[b])[m[:, 1]])
    return out


@dataclass(frozen=True, kw_only=True)
class OutlierCounts:
    """GT outliers among the stored matches (see the module docstring).

    Attributes:
        num_pairs: pairs measured (both images in the GT, at least one match).
        num_matches: their matches.
        num_correct: matches within ``threshold_px`` of their GT epipolar line.
        num_outliers: the others (a NaN distance, from a degenerate GT pair, counts as outlier).
        outlier_share: ``num_outliers / num_matches`` (0 when there is no match).
        num_correct_pairs: pairs whose median distance is within ``threshold_px``.
        correct_pair_matches / correct_pair_outliers: matches and GT outliers of those pairs.
        correct_pair_outlier_share: their ratio (0 when there is no correct pair).
        threshold_px: the threshold used.
    """

    num_pairs: int
    num_matches: int
    num_correct: int
    num_outliers: int
    outlier_share: float
    num_correct_pairs: int
    correct_pair_matches: int
    correct_pair_outliers: int
    correct_pair_outlier_share: float
    threshold_px: float

    def to_dict(self) -> dict:
        return asdict(self)


def outlier_counts(distances: Mapping[object, np.ndarray], threshold_px: float = ORACLE_THRESHOLD_PX
                   ) -> OutlierCounts:
    """Count correct matches and GT outliers of per-pair distance arrays (see :class:`OutlierCounts`)."""
    if not threshold_px > 0:
        raise ValueError(f"threshold_px must be > 0, got {threshold_px}")
    n = correct = pairs = cp = cp_n = cp_out = 0
    for d in distances.values():
        d = np.asarray(d, dtype=np.float64)
        if d.size == 0:
            continue
        ok = int(np.count_nonzero(d <= threshold_px))  # NaN compares False: an outlier
        pairs += 1
        n += d.size
        correct += ok
        if np.median(np.where(np.isfinite(d), d, np.inf)) <= threshold_px:
            cp += 1
            cp_n += d.size
            cp_out += d.size - ok
    return OutlierCounts(num_pairs=pairs, num_matches=n, num_correct=correct, num_outliers=n - correct,
                         outlier_share=(n - correct) / n if n else 0.0, num_correct_pairs=cp,
                         correct_pair_matches=cp_n, correct_pair_outliers=cp_out,
                         correct_pair_outlier_share=cp_out / cp_n if cp_n else 0.0, threshold_px=float(threshold_px))


@dataclass(frozen=True, kw_only=True)
class OracleStats:
    """What :func:`write_oracle_database` removed.

    Attributes:
        num_pairs: verified pairs of the input.
        num_pairs_without_gt: of those, pairs with an image outside the GT (left as they were).
        num_pairs_emptied: pairs left without matches (their two-view geometry removed).
        num_matches_in / num_matches_removed: stored inliers of the judged pairs, and how many
            were removed.
        threshold_px: the threshold used.
    """

    num_pairs: int
    num_pairs_without_gt: int
    num_pairs_emptied: int
    num_matches_in: int
    num_matches_removed: int
    threshold_px: float

    def to_dict(self) -> dict:
        return asdict(self)


def write_oracle_database(database: str | Path, output: str | Path, gt: Mapping[str, object], *,
                          threshold_px: float = ORACLE_THRESHOLD_PX, keep_model: bool = True) -> OracleStats:
    """Write ``output``: a copy of ``database`` without the matches farther than
    ``threshold_px`` from their GT epipolar line (see the module docstring).

    Args:
        database: COLMAP database (read through a copy, never changed).
        output: the new database; must not exist.
        gt: image name -> camera with ``K, R, t`` (e.g. :func:`~.gt_model.load_gt_poses`).
        threshold_px: the GT-outlier threshold (symmetric epipolar distance, px).
        keep_model: keep each pair's stored two-view model (F/E/H, config), as ``refine``
            does; False fits a fundamental matrix to the kept matches instead.

    Raises:
        FileExistsError: ``output`` exists.
        DatabaseError: ``database`` is missing or not a COLMAP database.
    """
    from colmap_miho.adapters.database import ColmapDatabase, validate_database
    from colmap_miho.adapters.safety import read_copy

    if not threshold_px > 0:
        raise ValueError(f"threshold_px must be > 0, got {threshold_px}")
    output = Path(output)
    if output.exists():
        raise FileExistsError(f"{output} exists: the oracle database is written only where none is")
    output.parent.mkdir(parents=True, exist_ok=True)
    read_copy(database, output)
    validate_database(output, name=database)
    n_pairs = no_gt = emptied = n_in = n_removed = 0
    with ColmapDatabase(output) as db:
        names = {r.image_id: r.name for r in db.images()}
        keypoints: dict[int, np.ndarray] = {}
        with db.transaction():
            for pair in db.pairs("verified"):
                i, j = pair.image_id1, pair.image_id2
                n_pairs += 1
                a, b = names.get(i), names.get(j)
                if a is None or b is None or a not in gt or b not in gt:
                    no_gt += 1
                    continue
                for k in (i, j):
                    if k not in keypoints:
                        keypoints[k] = db.keypoints(k)
                m = db.matches(i, j, "verified")
                xy1, xy2 = keypoints[i][m[:, 0]], keypoints[j][m[:, 1]]
                keep = pair_distances(gt[a], gt[b], xy1, xy2) <= threshold_px
                n_in += len(m)
                if keep.all():
                    continue
                n_removed += int(np.count_nonzero(~keep))
                emptied += int(not keep.any())
                db.write_pair(i, j, m[keep], xy1[keep], xy2[keep], keep_model=keep_model)
    return OracleStats(num_pairs=n_pairs, num_pairs_without_gt=no_gt, num_pairs_emptied=emptied,
                       num_matches_in=n_in, num_matches_removed=n_removed, threshold_px=float(threshold_px))
