"""What a file of the run store read back must be before it is trusted: a damaged or forged file is
:class:`StoreDamaged` (one line naming it and ``--restart``), never a crash or lost matches."""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError

#: (image id -> (keypoint indices int64 (K,), new positions float64 (K, 2) pixels), stats)
GroupResult = tuple[dict[int, tuple[np.ndarray, np.ndarray]], dict]


class StoreDamaged(UserError):
    """A file of the run store cannot be read (truncated, overwritten, unreadable)."""

    def __init__(self, path: Path, why: object) -> None:
        text = " ".join(str(why).split()) or type(why).__name__
        super().__init__(f"the interrupted run's file {path} is damaged ({text}); pass --restart to discard "
                         "that run's work and start again")


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of the store file ``path``, read now; StoreDamaged for a truncated or foreign file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {key: z[key] for key in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise StoreDamaged(path, exc) from None


def stored_array(arrays: dict[str, np.ndarray], key: str, path: Path) -> np.ndarray:
    """``arrays[key]``, or :class:`StoreDamaged` naming ``path`` when the file lacks it."""
    try:
        return arrays[key]
    except KeyError:
        raise StoreDamaged(path, f"no array {key!r}") from None


@dataclass(frozen=True)
class ChunkIndex:
    """What the store keeps in memory of one filter chunk."""

    pairs: np.ndarray  # int64 (P, 2)
    success: np.ndarray  # bool (P,)
    matches: int  # over the successful pairs
    kept: int
    top: np.ndarray  # int64 (P, 2): each pair's largest keypoint index in each image, -1 for none


def _json_type(value: object) -> str:
    names = {type(None): "null", bool: "a boolean", int: "a number", float: "a number", str: "a string",
             list: "a list", dict: "an object"}
    return names.get(type(value), type(value).__name__)


def read_manifest(path: Path) -> dict:
    """The manifest at ``path``, its values' types checked; StoreDamaged otherwise."""
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StoreDamaged(path, "it is missing") from None
    except (OSError, ValueError, RecursionError) as exc:  # truncated, overwritten, unreadable, nested past reading
        raise StoreDamaged(path, getattr(exc, "strerror", None) or exc) from None
    if not isinstance(manifest, dict):
        raise StoreDamaged(path, f"it is {_json_type(manifest)}, not a JSON object")
    fingerprint = manifest.get("fingerprint")
    if not isinstance(fingerprint, dict):
        raise StoreDamaged(path, f"its fingerprint is {_json_type(fingerprint)}, not an object")
    recipe = fingerprint.get("recipe", {})
    if not isinstance(recipe, dict):
        raise StoreDamaged(path, f"its recipe is {_json_type(recipe)}, not an object")
    for name, table in recipe.items():
        if not isinstance(table, dict):
            raise StoreDamaged(path, f"its recipe table {name!r} is {_json_type(table)}, not an object")
    run_id = manifest.get("run_id")
    if not isinstance(run_id, str) or not run_id:
        raise StoreDamaged(path, f"its run_id is {_json_type(run_id) if run_id != '' else 'empty'}, "
                                 "not the run's id (a non-empty string)")
    if not isinstance(manifest.get("refine_plan", {}), dict):
        raise StoreDamaged(path, f"its refine_plan is {_json_type(manifest['refine_plan'])}, not an object")
    return manifest


#: numpy dtype kinds an array of the store may have, by what it holds.
_KINDS = {"b": "booleans", "iu": "integers", "f": "floats"}


def check_array(arrays: dict[str, np.ndarray], key: str, path: Path, kinds: str,
                shape: tuple[int | None, ...]) -> np.ndarray:
    """``arrays[key]`` checked to be of a dtype in ``kinds`` and of ``shape`` (None: any length),
    integers as int64; StoreDamaged otherwise."""
    a = stored_array(arrays, key, path)
    want = " x ".join("N" if n is None else str(n) for n in shape) or "a scalar"
    if a.dtype.kind not in kinds or a.ndim != len(shape) or any(
            n is not None and m != n for m, n in zip(a.shape, shape, strict=True)):
        raise StoreDamaged(path, f"its array {key!r} is {a.dtype} {tuple(a.shape)}, not {_KINDS[kinds]} of "
                                 f"shape ({want})")
    if a.dtype.kind == "u" and a.size and int(a.max()) > np.iinfo(np.int64).max:
        raise StoreDamaged(path, f"its array {key!r} holds integers beyond int64")
    return a.astype(np.int64) if kinds == "iu" else a


def check_offsets(offsets: np.ndarray, rows: int, key: str, path: Path) -> np.ndarray:
    """``offsets`` ``(P + 1,)`` checked to start at 0, never go back and end at ``rows``."""
    counts = np.diff(offsets)
    if len(offsets) == 0 or offsets[0] != 0 or (counts < 0).any() or offsets[-1] != rows:
        raise StoreDamaged(path, f"its {key} do not run from 0 up to its {rows} rows")
    return counts


def check_unique_pairs(pairs: np.ndarray, path: Path, key: str = "pairs") -> None:
    """Refuse a ``(P, 2)`` array of pairs holding one pair twice (StoreDamaged naming it)."""
    if len(pairs) > 1:
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        same = np.flatnonzero((np.diff(pairs[order], axis=0) == 0).all(axis=1))
        if len(same):
            a, b = pairs[order[same[0]]]
            raise StoreDamaged(path, f"its {key} hold pair ({a}, {b}) twice")


def check_filter_chunk(z: dict[str, np.ndarray], path: Path) -> ChunkIndex:
    """A filter chunk's arrays checked against each other; returns its index entry."""
    pairs = check_array(z, "pairs", path, "iu", (None, 2))
    n = len(pairs)
    ok = check_array(z, "success", path, "b", (n,))
    matches = check_array(z, "matches", path, "iu", (None, 2))
    rows = check_offsets(check_array(z, "offsets", path, "iu", (n + 1,)), len(matches), "offsets", path)
    homs = check_array(z, "patch_homographies", path, "f", (None, 2, 3, 3))
    hoff = check_array(z, "hom_offsets", path, "iu", (n + 1,))
    per_pair = check_offsets(hoff, len(homs), "hom_offsets", path)
    inliers = check_array(z, "inliers", path, "b", (len(matches),))
    labels = check_array(z, "labels", path, "iu", (len(matches),))
    kept = check_array(z, "kept", path, "iu", (n,))
    if (rows[~ok] != 0).any() or (per_pair[~ok] != 0).any() or (kept[~ok] != 0).any():
        raise StoreDamaged(path, "its offsets or kept counts give rows to a pair that failed")
    check_unique_pairs(pairs, path)
    if (matches < 0).any():
        raise StoreDamaged(path, "its matches hold negative keypoint indices")
    if not np.isfinite(homs).all():
        raise StoreDamaged(path, "its patch_homographies are not all finite")
    row_pair = np.repeat(np.arange(n), rows)
    if (kept != np.bincount(row_pair[inliers], minlength=n)).any():
        raise StoreDamaged(path, "its kept counts differ from its inliers")
    if ((labels < -1) | (labels >= np.repeat(per_pair, rows)) | (inliers & (labels < 0))).any():
        raise StoreDamaged(path, "its labels name patch homographies their pair does not have")
    top = np.full((n, 2), -1, np.int64)
    full = np.flatnonzero(rows > 0)
    if len(full):
        top[full] = np.maximum.reduceat(matches, np.asarray(rows.cumsum() - rows)[full], axis=0)
    return ChunkIndex(pairs=pairs, success=ok, matches=int(rows[ok].sum()), kept=int(kept[ok].sum()), top=top)


#: The one group stat that is not a counter: image id (a string, in JSON) -> decodes
#: (``track_groups.DECODED_BY_IMAGE``).
DECODED_BY_IMAGE = "decoded_by_image"


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_count(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


#: Pixels a moved keypoint may lie outside its image: a refinement moves a keypoint by less than
#: its NCC window (template + search radius, at most 64 px), from at most
#: :data:`~colmap_miho.adapters.conventions.KEYPOINT_MARGIN_PX` outside; farther, a stored
#: position is forged (written as it is, ``1e300`` would be an infinite keypoint in the output).
MOVED_MARGIN_PX = 64.0


def check_group(z: dict[str, np.ndarray], path: Path, num_keypoints: dict[int, int] | None,
                image_sizes: Mapping[int, tuple[int, int]] | None = None) -> GroupResult:
    """A refine group's arrays checked against each other and the images' keypoint counts and sizes;
    returns (moved, stats)."""
    ids = check_array(z, "image_ids", path, "iu", (None,))
    idx = check_array(z, "idx", path, "iu", (None,))
    xy = check_array(z, "xy", path, "f", (len(idx), 2))
    sizes = check_offsets(check_array(z, "offsets", path, "iu", (len(ids) + 1,)), len(idx), "offsets", path)
    if len(np.unique(ids)) != len(ids):
        raise StoreDamaged(path, "its image_ids hold an image twice")
    if not np.isfinite(xy).all():
        raise StoreDamaged(path, "its positions xy are not all finite")
    try:
        stats = json.loads(str(stored_array(z, "stats", path)))
    except (ValueError, RecursionError) as exc:  # not JSON, or nested past reading
        raise StoreDamaged(path, f"its stats are not JSON ({exc})") from None
    if not isinstance(stats, dict):
        raise StoreDamaged(path, f"its stats are {_json_type(stats)}, not an object")
    for key, value in stats.items():  # counters, summed over the groups; decodes per image id
        if key == DECODED_BY_IMAGE:
            if not (isinstance(value, dict) and all(k.isdigit() and _is_count(v) for k, v in value.items())):
                raise StoreDamaged(path, f"its stats' {key} is not image id -> count")
        elif not _is_number(value):
            raise StoreDamaged(path, f"its stats' {key} is {_json_type(value)}, not a number")
        elif not (math.isfinite(value) and value >= 0):  # counters and seconds: the summary adds them up
            raise StoreDamaged(path, f"its stats' {key} is {value}, not a count")
    moved: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    start = 0
    for image_id, size in zip(ids.tolist(), sizes.tolist(), strict=True):
        rows = slice(start, start + size)
        start += size
        n = None if num_keypoints is None else num_keypoints.get(image_id)
        if num_keypoints is not None and n is None:
            raise StoreDamaged(path, f"it moves keypoints of image {image_id}, which is not in the database")
        if size and idx[rows].min() < 0:
            raise StoreDamaged(path, f"it moves negative keypoint indices of image {image_id}")
        if size and n is not None and idx[rows].max() >= n:
            raise StoreDamaged(path, f"it moves keypoint {idx[rows].max()} of image {image_id}, which has {n} "
                                     "keypoints")
        _check_inside(xy[rows], (image_sizes or {}).get(image_id), image_id, path)
        moved[image_id] = (idx[rows], xy[rows])
    return moved, stats


def _check_inside(xy: np.ndarray, size: tuple[int, int] | None, image_id: int, path: Path) -> None:
    """Refuse positions farther than :data:`MOVED_MARGIN_PX` outside an image of ``size``."""
    if not len(xy) or not size or not (size[0] and size[1]):
        return
    lo, hi = -0.5 - MOVED_MARGIN_PX, np.array(size, np.float64) - 0.5 + MOVED_MARGIN_PX
    bad = ((xy < lo) | (xy > hi)).any(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise StoreDamaged(path, f"it moves a keypoint of image {image_id} to ({xy[k, 0]:g}, {xy[k, 1]:g}), outside "
                                 f"the {size[0]}x{size[1]} image")
