"""Read and write hloc / deep-image-matching HDF5 features and matches, one image or pair at a time.

Features: a group per image with ``keypoints`` ``(N, 2)`` pixels (integer = pixel centre). Matches,
told apart per pair: hloc's ``matches0`` ``(N0,)`` (-1 = unmatched) under ``f(name0)/f(name1)`` or
``f(name0)_f(name1)``, ``f(n) = n.replace('/', '-')``; or deep-image-matching's ``name0/name1``
``(M, 2)``."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import InvalidInput
from .h5_checks import (
    KEYPOINT_BYTES,
    READ_BUDGET_BYTES,
    check_budget,
    check_dataset,
    check_keypoints_in_image,
    check_numeric,
    h5_reader,
)

log = logging.getLogger(__name__)

MATCHES0 = "matches0"
SCORES0 = "matching_scores0"


def flat_name(name: str) -> str:
    """hloc's pair-key form of an image name: every ``/`` replaced by ``-``."""
    return name.replace("/", "-")


def pair_key(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's key of the pair group (``separator='_'`` gives the legacy key)."""
    return f"{flat_name(name0)}{separator}{flat_name(name1)}"


def open_h5(path: str | Path, mode: str = "r") -> h5py.File:
    """Open an HDF5 file, with a one-line error naming the file when it is missing or not HDF5."""
    path = Path(path)
    if mode == "r" and not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if mode == "r" and not h5py.is_hdf5(path):
        raise InvalidInput(f"{path}: not an HDF5 file")
    try:
        return h5py.File(path, mode)
    except OSError as exc:  # truncated or damaged: h5py's message does not name the file
        raise InvalidInput(f"{path}: cannot open the HDF5 file, damaged or truncated ({exc})") from None


@dataclass(frozen=True)
class ImageFeatures:
    """Keypoints of one image: ``keypoints`` ``(N, 2)`` float64 pixels, ``scores`` ``(N,)`` or None,
    ``shapes`` ``(N, 2, 2)`` affine frames (from ``scales``/``oris``) or None."""

    name: str
    keypoints: np.ndarray
    scores: np.ndarray | None = None
    shapes: np.ndarray | None = None


@dataclass(frozen=True)
class PairMatches:
    """Matches of one pair: ``matches`` ``(M, 2)`` int64 (name0, name1), ``scores`` ``(M,)`` or None."""

    name0: str
    name1: str
    matches: np.ndarray
    scores: np.ndarray | None = None


# ---------------------------------------------------------------------------------------------
# features


#: Datasets an hloc / deep-image-matching features file holds per image besides ``keypoints``:
#: a group holding one of them but no ``keypoints`` is an image whose keypoints are missing.
IMAGE_DATASETS = frozenset({"descriptors", "scores", "image_size", "scales", "oris"})


@h5_reader
def list_feature_images(h5: h5py.File) -> list[str]:
    """Image names of a features file: every group with a ``keypoints`` dataset, in file order."""
    names: list[str] = []
    keypoint_groups: list[str] = []  # a 'keypoints' that is a group, not a dataset
    without: dict[str, list[str]] = {}  # image group -> its per-image datasets, no 'keypoints'

    def visit(path: str, obj) -> None:
        leaf = path.rsplit("/", 1)[-1]
        if leaf == "keypoints":
            if isinstance(obj, h5py.Dataset):
                names.append(obj.parent.name.strip("/"))
            else:
                keypoint_groups.append(obj.parent.name.strip("/"))
        elif (isinstance(obj, h5py.Dataset) and leaf in IMAGE_DATASETS and obj.parent.name != "/"
              and "keypoints" not in obj.parent):
            without.setdefault(obj.parent.name.strip("/"), []).append(leaf)

    h5.visititems(visit)
    # an image group the pairs may name: say what is wrong with it, not "not in the features file"
    if keypoint_groups:
        raise InvalidInput(f"{h5.filename}: 'keypoints' of image {keypoint_groups[0]!r} is a group, expected an "
                           "(N, 2) dataset" + (f" (and {len(keypoint_groups) - 1} more images)"
                                               if len(keypoint_groups) > 1 else ""))
    if without:
        name, held = next(iter(without.items()))
        raise InvalidInput(f"{h5.filename}: image {name!r} has no 'keypoints' dataset (it holds {', '.join(held)})"
                           + (f"; and {len(without) - 1} more such images" if len(without) > 1 else ""))
    if not names:
        raise InvalidInput(f"{h5.filename}: no group with a 'keypoints' dataset (not a features file?)")
    return names


@h5_reader
def read_features(h5: h5py.File, name: str, *, budget_bytes: int = READ_BUDGET_BYTES,
                  image_size: tuple[int, int] | None = None, origin: float = -0.5) -> ImageFeatures:
    """Read the keypoints of image ``name``, shapes and dtypes checked before reading, then values
    finite and inside ``image_size``. ValueError names the file and the image."""
    if name not in h5 or not isinstance(h5[name], h5py.Group) or "keypoints" not in h5[name]:
        raise InvalidInput(f"{h5.filename}: image {name!r} has no 'keypoints' group/dataset")
    grp = h5[name]
    ds = check_dataset(h5, grp["keypoints"], f"'keypoints' of image {name!r}")
    what = f"keypoints of image {name!r}"
    if len(ds.shape) != 2 or ds.shape[1] != 2:
        raise InvalidInput(f"{h5.filename}: {what} have shape {ds.shape}, expected (N, 2)")
    check_numeric(h5, ds, what)
    check_budget(h5, ds.shape[0] * KEYPOINT_BYTES, f"{what} ({ds.shape[0]} rows)", budget_bytes)
    kp = np.asarray(ds[()], dtype=np.float64)
    if not np.isfinite(kp).all():
        raise InvalidInput(f"{h5.filename}: {what} contain NaN or inf")
    if image_size is not None:
        check_keypoints_in_image(h5, kp, image_size, what, origin)
    n = len(kp)
    scores = _optional_vector(h5, grp, "scores", n, name)
    shapes = None
    scales, oris = _optional_vector(h5, grp, "scales", n, name), _optional_vector(h5, grp, "oris", n, name)
    if scales is not None and oris is not None:
        c, s = np.cos(oris), np.sin(oris)
        rotations = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        shapes = (scales[:, None, None] * rotations).astype(np.float32)
    return ImageFeatures(name=name, keypoints=kp, scores=scores, shapes=shapes)


def _optional_vector(h5: h5py.File, grp: h5py.Group, key: str, n: int, name: str) -> np.ndarray | None:
    if key not in grp:
        return None
    ds = check_dataset(h5, grp[key], f"'{key}' of image {name!r}")
    size = int(np.prod(ds.shape)) if ds.shape is not None else 0
    if size != n:
        raise InvalidInput(f"{h5.filename}: image {name!r}: '{key}' has {size} values for {n} keypoints")
    check_numeric(h5, ds, f"'{key}' of image {name!r}")
    v = np.asarray(ds[()], dtype=np.float32).reshape(-1)
    if not np.isfinite(v).all():
        raise InvalidInput(f"{h5.filename}: image {name!r}: '{key}' contains NaN or inf")
    return v


def write_features(h5: h5py.File, name: str, keypoints: np.ndarray, image_size: tuple[int, int] | None = None) -> None:
    """Write one image group (``keypoints`` float32, optional ``image_size``), replacing an existing one."""
    kp = np.asarray(keypoints, dtype=np.float32)
    if kp.ndim != 2 or kp.shape[1] != 2:
        raise InvalidInput(f"keypoints of image {name!r} have shape {kp.shape}, expected (N, 2)")
    if name in h5:
        del h5[name]
    grp = h5.create_group(name)
    grp.create_dataset("keypoints", data=kp)
    if image_size is not None:
        grp.create_dataset("image_size", data=np.asarray(image_size, dtype=np.int64))


@h5_reader
def count_rows(h5: h5py.File, leaf: str) -> int:
    """Total first dimension of every dataset named ``leaf``, from the shapes alone."""
    total = 0

    def visit(path: str, obj) -> None:
        nonlocal total
        if isinstance(obj, h5py.Dataset) and path.rsplit("/", 1)[-1] == leaf and obj.shape:
            total += int(obj.shape[0])

    h5.visititems(visit)
    return total


@h5_reader
def count_matches(h5: h5py.File) -> int:
    """An upper bound of a matches file's matches from its datasets' shapes alone."""
    total = 0

    def visit(path: str, obj) -> None:
        nonlocal total
        if isinstance(obj, h5py.Dataset) and path.rsplit("/", 1)[-1] != SCORES0 and obj.shape:
            total += int(obj.shape[0])

    h5.visititems(visit)
    return total


# ---------------------------------------------------------------------------------------------
# matches


class _NameIndex:
    def __init__(self, names: Iterable[str]):
        self.names = set(names)
        self.by_flat: dict[str, str] = {}
        for n in self.names:
            other = self.by_flat.setdefault(flat_name(n), n)
            if other != n:
                raise InvalidInput(f"images {other!r} and {n!r} have the same hloc pair name {flat_name(n)!r}")

    def lookup(self, part: str) -> str | None:
        return part if part in self.names else self.by_flat.get(part)

    def split(self, key: str) -> tuple[str, str]:
        """Split a pair key ``a/b`` or ``a_b`` into two known image names."""
        found = set()
        for i, ch in enumerate(key):
            if ch in "/_":
                a, b = self.lookup(key[:i]), self.lookup(key[i + 1 :])
                if a is not None and b is not None:
                    found.add((a, b))
        if not found:
            half = [key[i + 1 :] if self.lookup(key[:i]) else key[:i]
                    for i, ch in enumerate(key) if ch in "/_" and (self.lookup(key[:i]) or self.lookup(key[i + 1 :]))]
            what = f"image {half[0]!r}" if len(half) == 1 else "an image"
            raise InvalidInput(f"pair {key!r} in the matches file names {what} that is not in the features file")
        if len(found) > 1:
            raise InvalidInput(f"pair {key!r} is ambiguous: it splits into {sorted(found)}")
        return found.pop()


@h5_reader
def _pair_datasets(h5: h5py.File) -> list[tuple[str, str]]:
    """(pair key, layout) for every pair of a matches file; layout is 'hloc' or 'dim'."""
    out: list[tuple[str, str]] = []
    dropped: list[str] = []

    def visit(path: str, obj) -> None:
        if isinstance(obj, h5py.Group):
            if not len(obj):
                dropped.append(path)
            return
        leaf = path.rsplit("/", 1)[-1]
        if leaf == SCORES0 and MATCHES0 not in obj.parent:
            dropped.append(obj.parent.name.strip("/"))
        elif leaf == MATCHES0:
            out.append((obj.parent.name.strip("/"), "hloc"))
        elif leaf != SCORES0 and MATCHES0 not in obj.parent:
            if len(obj.shape) != 2 or obj.shape[1] != 2 or not np.issubdtype(obj.dtype, np.integer):
                raise InvalidInput(
                    f"{h5.filename}: dataset {path!r} (shape {obj.shape}, {obj.dtype}) is neither hloc's "
                    f"'{MATCHES0}' nor a deep-image-matching (M, 2) integer match array (not a matches file?)"
                )
            out.append((path, "dim"))

    h5.visititems(visit)
    if dropped:
        log.warning("%s: %d pair group(s) without '%s' skipped (nothing to import in them), e.g. %r",
                    h5.filename, len(dropped), MATCHES0, dropped[0])
    return out


def _as_int64(values: np.ndarray, what: str, n0: int, n1: int) -> np.ndarray:
    """Integer match indices as int64; a uint64 value above int64's range is refused (InvalidInput)."""
    if values.dtype.kind == "u" and values.dtype.itemsize >= 8:
        too_big = values > np.uint64(np.iinfo(np.int64).max)
        if too_big.any():
            flat = int(np.flatnonzero(too_big.reshape(-1))[0])
            raise InvalidInput(f"{what}: keypoint index {int(values.reshape(-1)[flat])} out of range in entry "
                               f"{flat // (values.shape[1] if values.ndim == 2 else 1)} (images have {n0} and {n1} "
                               "keypoints; an unsigned array cannot hold -1 for 'unmatched')")
    return values.astype(np.int64)


@h5_reader
def _read_pair(h5: h5py.File, key: str, layout: str, name0: str, name1: str, n0: int, n1: int,
               budget_bytes: int = READ_BUDGET_BYTES) -> PairMatches:
    """One pair's matches, checked; repeated rows dropped with a warning."""
    label = f"pair ({name0!r}, {name1!r})"
    if layout == "hloc":
        grp = h5[key]
        ds = check_dataset(h5, grp[MATCHES0], f"{label}: '{MATCHES0}'")
        if len(ds.shape) != 1 or ds.dtype.kind not in "iu":
            raise InvalidInput(f"{label}: '{MATCHES0}' has shape {ds.shape} dtype {ds.dtype}, expected (N0,) integers")
        if ds.shape[0] != n0:
            raise InvalidInput(f"{label}: '{MATCHES0}' has {ds.shape[0]} entries but image {name0!r} "
                               f"has {n0} keypoints")
        m0 = _as_int64(np.asarray(ds[()]), f"{label}: '{MATCHES0}'", n0, n1)
        idx0 = np.flatnonzero(m0 > -1)
        matches = np.stack([idx0, m0[idx0]], axis=1).astype(np.int64)
        scores = None
        if SCORES0 in grp:
            sd = check_dataset(h5, grp[SCORES0], f"{label}: '{SCORES0}'")
            if int(np.prod(sd.shape)) != n0 or sd.dtype.kind not in "fiu":
                raise InvalidInput(f"{label}: '{SCORES0}' has shape {sd.shape} dtype {sd.dtype}, expected ({n0},) "
                                 "real numbers")
            s0 = np.asarray(sd[()], dtype=np.float32).reshape(-1)
            scores = s0[idx0]
    else:
        ds = check_dataset(h5, h5[key], f"{label}: matches")
        if len(ds.shape) != 2 or ds.shape[1] != 2 or ds.dtype.kind not in "iu":
            raise InvalidInput(f"{label}: matches have shape {ds.shape} dtype {ds.dtype}, "
                             "expected (M, 2) integers")
        if ds.shape[0] > n0 * n1:
            raise InvalidInput(f"{label}: {ds.shape[0]} matches, more than the {n0} x {n1} keypoint pairs")
        check_budget(h5, ds.shape[0] * 32, f"{label}: {ds.shape[0]} matches", budget_bytes)
        matches = _as_int64(np.asarray(ds[()]), f"{label}: matches", n0, n1)
        scores = None
    bad = (matches < 0) | (matches >= np.array([n0, n1]))
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        raise InvalidInput(
            f"{label}: keypoint index out of range in match {row}: {matches[row].tolist()} "
            f"(images have {n0} and {n1} keypoints)"
        )
    if len(matches) > 1:
        _, first = np.unique(matches, axis=0, return_index=True)
        if len(first) < len(matches):
            keep = np.sort(first)
            log.warning("%s: %d repeated match rows dropped (each (i, j) is stored once)", label,
                        len(matches) - len(keep))
            matches = matches[keep]
            scores = scores[keep] if scores is not None else None
    return PairMatches(name0=name0, name1=name1, matches=matches, scores=scores)


def iter_matches(
    h5: h5py.File,
    num_keypoints: dict[str, int],
    pairs: Iterable[tuple[str, str]] | None = None,
) -> Iterator[PairMatches]:
    """Yield :class:`PairMatches` one pair at a time (layouts may mix); ``pairs`` restricts and
    orients them (ValueError for a missing one); a pair already yielded is skipped."""
    index = _NameIndex(num_keypoints)
    todo: Iterable[tuple[str, str, str, str, bool]]
    if pairs is None:
        todo = [(key, layout, *index.split(key), False) for key, layout in _pair_datasets(h5)]
    else:
        todo = (_find_pair(h5, n0, n1) for n0, n1 in pairs)
    seen: set[frozenset[str]] = set()
    for key, layout, name0, name1, reverse in todo:
        for n in (name0, name1):
            if n not in num_keypoints:
                raise InvalidInput(f"pair ({name0!r}, {name1!r}): image {n!r} is not in the features file")
        if name0 == name1:
            raise InvalidInput(f"pair ({name0!r}, {name1!r}) matches an image with itself")
        unordered = frozenset((name0, name1))
        if unordered in seen:
            log.debug("pair (%s, %s) seen already: skipped", name0, name1)
            continue
        seen.add(unordered)
        if reverse:  # stored as (name1, name0) in the file
            pm = _read_pair(h5, key, layout, name1, name0, num_keypoints[name1], num_keypoints[name0])
            yield PairMatches(name0=name0, name1=name1, matches=pm.matches[:, ::-1].copy(), scores=pm.scores)
        else:
            yield _read_pair(h5, key, layout, name0, name1, num_keypoints[name0], num_keypoints[name1])


@h5_reader
def _find_pair(h5: h5py.File, name0: str, name1: str) -> tuple[str, str, str, str, bool]:
    """(key, layout, name0, name1, stored_reversed) of a pair from a pairs list, in any layout."""
    for a, b, reverse in ((name0, name1, False), (name1, name0, True)):
        for key, layout in ((pair_key(a, b, "/"), "hloc"), (pair_key(a, b, "_"), "hloc"), (f"{a}/{b}", "dim")):
            obj = h5.get(key)
            if layout == "hloc" and isinstance(obj, h5py.Group) and MATCHES0 in obj:
                return key, layout, name0, name1, reverse
            if layout == "dim" and isinstance(obj, h5py.Dataset):
                return key, layout, name0, name1, reverse
    raise InvalidInput(f"pair ({name0!r}, {name1!r}) from the pairs list is not in the matches file {h5.filename}")


def write_pair_matches(
    h5: h5py.File, pm: PairMatches, num_keypoints0: int, layout: str = "hloc"
) -> int:
    """Write one pair: ``'hloc'`` as ``matches0`` (a keypoint of image 0 keeps its first match only;
    returns how many were dropped) or ``'dim'`` as ``(M, 2)`` int64 (lossless, returns 0)."""
    m = np.asarray(pm.matches, dtype=np.int64).reshape(-1, 2)
    if layout == "dim":
        h5.create_dataset(f"{pm.name0}/{pm.name1}", data=m)
        return 0
    if layout != "hloc":
        raise InvalidInput(f"layout={layout!r} is not one of: hloc, dim")
    m0 = np.full(num_keypoints0, -1, dtype=np.int32)
    s0 = np.zeros(num_keypoints0, dtype=np.float32)
    first = np.unique(m[:, 0], return_index=True)[1]
    dropped = len(m) - len(first)
    scores = np.ones(len(m), np.float32) if pm.scores is None else np.asarray(pm.scores, np.float32)
    m0[m[first, 0]] = m[first, 1]
    s0[m[first, 0]] = scores[first]
    grp = h5.require_group(pair_key(pm.name0, pm.name1))
    grp.create_dataset(MATCHES0, data=m0)
    grp.create_dataset(SCORES0, data=s0)
    return dropped


def read_pairs_file(path: str | Path) -> list[tuple[str, str]]:
    """Read a pairs list: the first two whitespace-separated fields of each line (so both
    ``pairs.txt`` and ``pairs_with_gt.txt``); blank and ``#`` lines skipped. Returns ``[(name0,
    name1), ...]`` in file order. FileNotFoundError, or ValueError naming ``file:line``."""
    path = Path(path)
    pairs = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) < 2:
                raise InvalidInput(f"{path}:{lineno}: expected 'name0 name1 ...', got {line!r}")
            pairs.append((parts[0], parts[1]))
    return pairs
