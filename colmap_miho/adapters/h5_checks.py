"""Checks on an h5 file's datasets before they are read: a dataset (not a group), a real-number
dtype, and the memory its arrays would take against a budget, so that a damaged or foreign file
is one clear error instead of an out-of-memory kill.
"""

from __future__ import annotations

import h5py

from ..errors import InvalidInput

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
