"""An aerial survey with a planted hinge: consistent wrong pairs between two halves.

The survey of :func:`miho_bench.synthetic.survey_layout` is split into two halves by its flight
lines (A: the first half of the lines, B: the rest). A share of the points of A's area is
repeated in B's area: each copy is the original moved by one rigid motion ``T`` (a turn of
``turn_deg`` about the vertical, then a shift from A's centre to B's), as a second facade built
to the same plan would be. The copies are real points: B's images see them and match them among
themselves correctly. A *wrong pair* joins an image of A and one of B that do not overlap: it
matches each repeated point that the first sees with its copy in the second, as a matcher fooled
by the repetition does. All such pairs agree with one another: with them, group B is group A's
neighbour turned by ``T``. The *correct cross pairs* are the survey's own pairs between the two
halves (sequential + nearest neighbours), with the points both images see.

``wrong_per_right`` wrong pairs are planted for each correct cross pair (the ones with the most
matches first), so that a robust rotation average sides with the wrong ones from about 1:1 on,
and the wrong pairs hold more matches than the correct ones (a repeated element gives many).
Every image detects each point it sees with probability ``detect_prob``, so a correct pair
matches about that share of what both see; a wrong pair only the repeated share of it.

Each pair stores a fundamental matrix fitted to all its matches (as COLMAP's verification would),
on terrain of some relief (``relief``: a flat one makes every pair's F degenerate).

Ground truth: :attr:`HingedSurvey.correct` marks each stored match that joins two observations
of one true point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from colmap_miho.geometry import fit_fundamental

from .synthetic import SurveyLayout, survey_layout, survey_pairs, write_survey_database


@dataclass(frozen=True)
class HingedSurvey:
    """What :func:`make_hinged_survey` built.

    Attributes:
        database: the COLMAP database (one SIMPLE_RADIAL camera, matches stored as inliers).
        matches: pair of image ids -> int64 (M, 2) keypoint indices, as stored.
        correct: pair -> bool (M,): the match joins two observations of one true point.
        wrong_pairs: the planted wrong pairs; correct_cross: the true pairs between the halves.
        group_a / group_b: image ids of the two halves.
        layout: the survey (copies included in its points).
    """

    database: Path
    matches: dict[tuple[int, int], np.ndarray]
    correct: dict[tuple[int, int], np.ndarray]
    wrong_pairs: tuple[tuple[int, int], ...]
    correct_cross: tuple[tuple[int, int], ...]
    group_a: frozenset[int]
    group_b: frozenset[int]
    layout: SurveyLayout


def _yaw(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def make_hinged_survey(out_dir: str | Path, *, num_images: int = 24, wrong_per_right: float = 2.0,
                       repeated_share: float = 0.6, turn_deg: float = 40.0, detect_prob: float = 0.85,
                       points_per_image: int = 300, relief: float = 0.3, outlier_ratio: float = 0.05,
                       noise_px: float = 0.5,
                       min_pair_matches: int = 15, seed: int = 0) -> HingedSurvey:
    """Create ``out_dir/database.db`` for a survey with a planted hinge (module docstring).

    Raises:
        ValueError: an argument out of range; the message names it.
    """
    if not 0 < repeated_share < 1:
        raise ValueError(f"repeated_share must be in (0, 1), got {repeated_share}")
    if not 0 < detect_prob <= 1:
        raise ValueError(f"detect_prob must be in (0, 1], got {detect_prob}")
    if wrong_per_right < 0:
        raise ValueError(f"wrong_per_right must be >= 0, got {wrong_per_right}")
    rng = np.random.default_rng(seed + 7)
    base = survey_layout(num_images, points_per_image=points_per_image, relief=relief, seed=seed)
    line_x = np.unique(np.round(base.centres[:, 0], 1))
    cut = line_x[len(line_x) // 2]
    in_b = base.centres[:, 0] >= cut - 1e-9
    if in_b.all() or not in_b.any():
        raise ValueError(f"num_images={num_images} gives one flight line: no two halves")
    mid = 0.5 * (base.centres[~in_b, 0].max() + base.centres[in_b, 0].min())
    area_a, area_b = base.points[:, 0] < mid, base.points[:, 0] >= mid
    ca = np.r_[base.points[area_a, :2].mean(0), 0.0]
    cb = np.r_[base.points[area_b, :2].mean(0), 0.0]
    repeated = np.flatnonzero(area_a & (rng.random(len(base.points)) < repeated_share))
    R = _yaw(turn_deg)
    copies = (base.points[repeated] - ca) @ R.T + cb
    copy_of = np.full(len(base.points) + len(copies), -1, np.int64)
    copy_of[repeated] = len(base.points) + np.arange(len(copies))
    layout = replace(base, points=np.concatenate([base.points, copies]))

    seen, true_xy = [], []
    for k in range(num_images):
        idx, xy = layout.project(k)
        keep = rng.random(len(idx)) < detect_prob
        idx, xy = idx[keep], xy[keep]
        order = rng.permutation(len(idx))
        seen.append(idx[order])
        true_xy.append(xy[order])
    where = [{int(p): r for r, p in enumerate(s)} for s in seen]

    def true_matches(a: int, b: int) -> np.ndarray:
        _, ia, ib = np.intersect1d(seen[a], seen[b], assume_unique=True, return_indices=True)
        return np.stack([ia, ib], axis=1).astype(np.int64)

    def fooled_matches(a: int, b: int) -> np.ndarray:
        rows = [(r, where[b][int(copy_of[p])]) for r, p in enumerate(seen[a])
                if copy_of[p] >= 0 and int(copy_of[p]) in where[b]]
        return np.asarray(rows, np.int64).reshape(-1, 2)

    group_a = [k for k in range(num_images) if not in_b[k]]
    group_b = [k for k in range(num_images) if in_b[k]]
    natural = [(a, b) for a, b in survey_pairs(layout.centres) if len(true_matches(a, b)) >= min_pair_matches]
    cross = [(a, b) for a, b in natural if in_b[a] != in_b[b]]
    candidates = []
    for a in group_a:
        for b in group_b:
            if (min(a, b), max(a, b)) in natural:
                continue
            m = fooled_matches(a, b)
            if len(m) >= min_pair_matches:
                candidates.append((len(m), a, b, m))
    candidates.sort(key=lambda c: (-c[0], c[1], c[2]))
    planted = candidates[: int(round(wrong_per_right * len(cross)))]

    stored: dict[tuple[int, int], np.ndarray] = {}
    correct: dict[tuple[int, int], np.ndarray] = {}

    def store(a: int, b: int, m: np.ndarray, ok: np.ndarray) -> None:
        n_out = int(round(len(m) * outlier_ratio))
        free_a = np.setdiff1d(np.arange(len(seen[a])), m[:, 0])
        free_b = np.setdiff1d(np.arange(len(seen[b])), m[:, 1])
        n_out = min(n_out, len(free_a), len(free_b))
        if n_out:
            out = np.stack([rng.choice(free_a, n_out, replace=False), rng.choice(free_b, n_out, replace=False)], axis=1)
            m, ok = np.concatenate([m, out]), np.r_[ok, np.zeros(n_out, bool)]
        order = rng.permutation(len(m))
        m, ok = m[order], ok[order]
        if a > b:
            a, b, m = b, a, m[:, ::-1]
        stored[(a + 1, b + 1)] = np.ascontiguousarray(m)
        correct[(a + 1, b + 1)] = ok

    for a, b in natural:
        store(a, b, true_matches(a, b), np.ones(len(true_matches(a, b)), bool))
    for _, a, b, m in planted:
        store(a, b, m, np.zeros(len(m), bool))
    keypoints = {}
    for k in range(num_images):
        xy = true_xy[k] + rng.normal(0.0, noise_px, true_xy[k].shape)
        keypoints[k + 1] = np.clip(xy, 0, (layout.width - 1e-3, layout.height - 1e-3))
    database = Path(out_dir) / "database.db"
    database.parent.mkdir(parents=True, exist_ok=True)
    fundamental = {}
    for (a, b), m in stored.items():  # as COLMAP's verification fits it: to all the pair's matches
        F = fit_fundamental(keypoints[a][m[:, 0]], keypoints[b][m[:, 1]], np.random.default_rng([seed, a, b]))
        if F is not None:
            fundamental[(a, b)] = F
    write_survey_database(database, layout, keypoints, stored, fundamental)
    return HingedSurvey(
        database=database, matches=stored, correct=correct,
        wrong_pairs=tuple(sorted((min(a, b) + 1, max(a, b) + 1) for _, a, b, _ in planted)),
        correct_cross=tuple(sorted((a + 1, b + 1) for a, b in cross)),
        group_a=frozenset(k + 1 for k in group_a), group_b=frozenset(k + 1 for k in group_b), layout=layout)
