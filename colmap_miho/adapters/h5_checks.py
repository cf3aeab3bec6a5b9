"""Checks on an h5 file's datasets before they are read (a dataset, a real dtype, a memory budget),
so a damaged or foreign file is one clear error instead of an out-of-memory kill."""

from __future__ import annotations

import functools

import h5py

from ..errors import InvalidInput
from .conventions import KEYPOINT_MARGIN_PX

#: The most memory one dataset of an h5 file may ask for when it is read (its shape times the
#: bytes of the arrays made from it); the default memory budget of a run, ``pipeline.memory_budget_mb``.
READ_BUDGET_BYTES = 2048 * 2**20


#: Bytes held per keypoint while one image is imported: float64 (x, y), float32 shapes (2, 2)
#: and COLMAP's 6 float32 columns.
KEYPOINT_BYTES = 16 + 16 + 24


def check_dataset(h5: h5py.File, obj, what: str) -> h5py.Dataset:
    if not isinstance(obj, h5py.Dataset):
        raise InvalidInput(f"{h5.filename}: {what} is a group, expected a dataset")
    return obj


def check_numeric(h5: h5py.File, ds: h5py.Dataset, what: str, kinds: str = "fiu") -> None:
    """Refuse a dataset whose dtype is not a real number (bool, complex, strings, compound)."""
    if ds.dtype.kind not in kinds:
        expected = "integers" if kinds == "iu" else "real numbers"
        raise InvalidInput(f"{h5.filename}: {what} have dtype {ds.dtype}, expected {expected}")


def check_budget(h5: h5py.File, nbytes: float, what: str, budget: int) -> None:
    """Refuse, before reading, a dataset whose arrays would take more than ``budget`` bytes."""
    if nbytes > budget:
        raise InvalidInput(f"{h5.filename}: {what} would take {nbytes / 2**20:.0f} MiB in memory, more than the "
                         f"budget of {budget / 2**20:.0f} MiB (a damaged or foreign file?)")


def h5_reader(func):
    """Decorator: h5py's errors on a damaged file become one InvalidInput naming the file."""

    @functools.wraps(func)
    def wrapper(h5, *args, **kwargs):
        try:
            return func(h5, *args, **kwargs)
        except (OSError, RuntimeError, KeyError) as exc:
            text = " ".join(str(exc).split()) or type(exc).__name__
            raise InvalidInput(f"{h5.filename}: cannot read the HDF5 file, damaged or truncated ({text})") from None

    return wrapper


def check_keypoints_in_image(h5: h5py.File, keypoints, size: tuple[int, int], what: str, origin: float) -> None:
    """Refuse keypoints ``(N, 2)`` outside the image by more than :data:`KEYPOINT_MARGIN_PX`;
    ``origin`` is the image edge's coordinate (-0.5 with pixel centres at integers). InvalidInput."""
    import numpy as np

    if len(keypoints) == 0:
        return
    lo = origin - KEYPOINT_MARGIN_PX
    hi = np.array(size, dtype=np.float64) + origin + KEYPOINT_MARGIN_PX
    bad = ((keypoints < lo) | (keypoints > hi)).any(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise InvalidInput(f"{h5.filename}: {what}: keypoint {k} at ({keypoints[k, 0]:g}, {keypoints[k, 1]:g}) lies "
                           f"outside the {size[0]}x{size[1]} image ({int(bad.sum())} such keypoints; wrong image "
                           "or a damaged file?)")
