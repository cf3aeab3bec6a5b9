"""Read stage: images, keypoints and the pairs to filter from the working copy, and which
images can be read for refinement."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..adapters.database import ColmapDatabase, PairRecord
from ..adapters.images import ImageLoader
from ..enums import MatchSource
from ..errors import DatabaseError, UserError
from ..pipeline_config import PipelineConfig
from ..terminal import printable
from ..types import Pair

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ReadConfig:
    """What the read stage needs besides the database: the ``pipeline`` table, the image folder, the
    loader's byte budget, ``strict``, and the user's database name for messages."""

    pipeline: PipelineConfig
    image_dir: Path
    image_budget_bytes: int
    strict: bool = False
    database_name: Path | str = ""


@dataclass(frozen=True, kw_only=True)
class ReadOutput:
    """The database as later stages see it: ``keypoints`` (image id -> ``(N_i, 2)`` float64 pixels),
    the pairs ``to_filter`` and the lazy image ``loader``."""

    keypoints: dict[int, np.ndarray]
    to_filter: list[PairRecord]
    loader: ImageLoader


@dataclass(frozen=True, kw_only=True)
class ReadStats:
    """Counts of the read stage (``RefineSummary`` fields of the same names)."""

    num_images: int
    num_pairs: int
    pairs_passed: int
    keypoints_total: int
    matches_in: int = 0  # over every pair of the source: what the output is compared with
    images_missing: list[str] = field(default_factory=list)
    images_implausible: list[str] = field(default_factory=list)  # keypoints unrelated to the pixels
    decoded_by_image: dict[int, int] = field(default_factory=dict)  # image id -> decodes

    @property
    def image_decodes(self) -> int:
        return sum(self.decoded_by_image.values())


def run_read(db: ColmapDatabase, cfg: ReadConfig) -> tuple[ReadOutput, ReadStats]:
    """Read images, keypoints and pairs; check the images open when refining. DatabaseError for no
    images or pairs; UserError for a missing image with ``strict``."""
    pcfg = cfg.pipeline
    images = db.images()
    if not images:
        raise DatabaseError(f"database has no images: {cfg.database_name}")
    names = {im.image_id: im.name for im in images}
    keypoints = {im.image_id: db.keypoints(im.image_id) for im in images}
    for im in images:  # the filter would fail later on one pair, naming neither image nor file
        if not np.isfinite(keypoints[im.image_id]).all():
            raise DatabaseError(f"database {cfg.database_name}: keypoints of image {im.name!r} (id {im.image_id}) "
                                "contain NaN or inf; extract or import that image's features again")
        _check_inside(keypoints[im.image_id], im, cfg.database_name)
    pairs = db.pairs(pcfg.source)
    if not pairs:
        raise DatabaseError(
            f"database has no image pairs with {pcfg.source} matches: {cfg.database_name}"
            + (" (try --source raw)" if pcfg.source == MatchSource.VERIFIED and db.pairs(MatchSource.RAW)
               else " (it has no matches at all: run COLMAP's matching first)")
        )
    to_filter = [p for p in pairs if p.num_matches >= pcfg.min_matches]
    loader = ImageLoader(cfg.image_dir, names, max_cached=None, max_cached_bytes=cfg.image_budget_bytes,
                         expected_sizes={im.image_id: (im.width, im.height) for im in images})
    missing_names: list[str] = []
    implausible: list[str] = []
    if pcfg.refine_keypoints:
        _check_one_file_per_image(cfg, names)
        missing = loader.check_all(inspect=_plausibility_check(db, keypoints, names, loader, implausible))
        missing_names = [names[i] for i in missing]
        if missing and cfg.strict:
            raise UserError(f"image {printable(loader.path(missing[0]))} is {loader.problems[missing[0]]} (--strict)"
                            + (f"; and {len(missing) - 1} more" if len(missing) > 1 else "")
                            + "; fix it, or drop --strict to skip it")
        if missing and len(missing) == len(images):
            raise UserError(f"none of the {len(images)} images of {cfg.database_name} can be used from "
                            f"{cfg.image_dir} (e.g. {printable(loader.path(missing[0]))} is "
                            f"{loader.problems[missing[0]]}); "
                            "check --images, or pass --no-refine to filter only")
    stats = ReadStats(num_images=len(images), num_pairs=len(pairs),
                      pairs_passed=len(pairs) - len(to_filter), matches_in=sum(p.num_matches for p in pairs),
                      keypoints_total=int(sum(len(k) for k in keypoints.values())),
                      images_missing=missing_names, images_implausible=implausible,
                      decoded_by_image=dict(loader.decoded))
    return ReadOutput(keypoints=keypoints, to_filter=to_filter, loader=loader), stats


def _check_one_file_per_image(cfg: ReadConfig, names: dict[int, str]) -> None:
    """Warn (``strict``: refuse) when two image rows name one file: both would be refined against the same pixels."""
    from ..adapters.paths import names_of_one_file

    groups = names_of_one_file(cfg.image_dir, names)
    if not groups:
        return
    shown = "; ".join(" and ".join(f"{n!r} (id {i})" for i, n in g) for g in groups[:3]) + (
        f"; and {len(groups) - 3} more group(s)" if len(groups) > 3 else "")
    text = (f"{sum(len(g) for g in groups) - len(groups)} image row(s) of {cfg.database_name} name a file that "
            f"another row names already: {shown}")
    if cfg.strict:
        raise UserError(f"{text} (--strict); remove the extra rows, or drop --strict to refine them as they are")
    log.warning("%s: their keypoints are refined against the same pixels (one photo counted twice); remove the "
                "extra rows if that is not meant", text)


def _check_inside(kp: np.ndarray, im, database) -> None:
    """Refuse keypoints more than ``KEYPOINT_MARGIN_PX`` outside their image (DatabaseError naming it)."""
    from ..adapters.conventions import KEYPOINT_MARGIN_PX

    if len(kp) == 0 or not (im.width and im.height):
        return
    lo, hi = -0.5 - KEYPOINT_MARGIN_PX, np.array([im.width, im.height], np.float64) - 0.5 + KEYPOINT_MARGIN_PX
    bad = ((kp < lo) | (kp > hi)).any(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DatabaseError(f"database {database}: keypoint {k} of image {im.name!r} (id {im.image_id}) at "
                            f"({kp[k, 0]:g}, {kp[k, 1]:g}) lies outside the {im.width}x{im.height} image "
                            f"({int(bad.sum())} such keypoints); extract or import that image's features again")


def check_match_indices(matches: np.ndarray, n1: int, n2: int, pair: Pair,
                        database_name: Path | str = "") -> None:
    """Refuse matches whose keypoint indices pass the images' keypoint counts (DatabaseError)."""
    if not len(matches):
        return
    for col, n, image_id in ((0, n1, pair[0]), (1, n2, pair[1])):
        top = int(matches[:, col].max())
        if top >= n:
            raise DatabaseError(
                f"database {database_name}: a match of image pair {pair[0]}-{pair[1]} uses keypoint "
                f"{top} of image {image_id}, which has {n} keypoints; the matches do not belong to these "
                "keypoints (re-run matching, or re-import the features and matches together)")


def _plausibility_check(db: ColmapDatabase, keypoints: dict[int, np.ndarray], names: dict[int, str],
                        loader: ImageLoader, found: list[str]):
    """Warn about (and add to ``found``) images whose keypoints fit their pixels no better than
    chance (a file renamed or shuffled after extraction)."""
    from .plausibility import implausible, keypoint_support

    def inspect(image_id: int, image: np.ndarray) -> None:
        affine = db.keypoint_affines(image_id)
        scale = None if affine is None else np.sqrt(np.abs(np.linalg.det(affine)))
        share, sampled = keypoint_support(image, keypoints[image_id], scale, seed=image_id)
        if implausible(share, sampled):
            found.append(names[image_id])
            log.warning("image %s does not look like the image its keypoints were found in (%.0f%% of %d "
                        "sampled keypoints stand out from their surroundings; 50%% by chance): was the file "
                        "renamed or replaced after feature extraction?", loader.path(image_id), 100 * share,
                        sampled)

    return inspect


def read_affines(db: ColmapDatabase, image_ids) -> dict[int, np.ndarray] | None:
    """Keypoint affine shapes per image, or None when any image has none."""
    affines = {i: db.keypoint_affines(i) for i in image_ids}
    known = {i: a for i, a in affines.items() if a is not None}
    return known if len(known) == len(affines) else None
