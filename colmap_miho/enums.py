"""Closed choices used across colmap-miho (pure Python, cheap to import)."""

from __future__ import annotations

from enum import Enum
from typing import TypeVar

_E = TypeVar("_E", bound="StrEnum")


class StrEnum(str, Enum):
    """A ``str`` enum whose ``str()`` is its value (``enum.StrEnum`` needs Python 3.11)."""

    def __str__(self) -> str:  # pragma: no cover - trivial
        return str(self.value)

    @classmethod
    def parse(cls: type[_E], value: str | StrEnum, name: str = "value") -> _E:
        """Return the member for ``value`` or raise ``ValueError`` listing the choices."""
        if isinstance(value, cls):
            return value
        try:
            return cls(str(value).lower())
        except ValueError:
            choices = ", ".join(m.value for m in cls)
            raise ValueError(f"{name}={value!r} is not one of: {choices}") from None

    @classmethod
    def values(cls) -> list[str]:
        """The members' values, in definition order (for argparse ``choices``)."""
        return [m.value for m in cls]


class FilterMethod(StrEnum):
    """Match filter variants of the paper (Sec. 3.1-3.2, App. D)."""

    MOP = "mop"
    MOP_STAR = "mop_star"
    MOP_MIHO = "mop_miho"
    MOP_MIHO_STAR = "mop_miho_star"
    MOP_VSAC = "mop_vsac"


class MoveSide(StrEnum):
    """Which keypoint of a match NCC may move."""

    FIRST = "1"
    SECOND = "2"
    AUTO = "auto"


class MatchSource(StrEnum):
    """Which matches of a COLMAP database are filtered."""

    VERIFIED = "verified"  # two_view_geometries inlier matches
    RAW = "raw"  # tentative matches table


class Device(StrEnum):
    """Where the torch work runs."""

    AUTO = "auto"
    CPU = "cpu"
    CUDA = "cuda"


class Mapper(StrEnum):
    """pycolmap reconstruction pipelines."""

    INCREMENTAL = "incremental"
    GLOBAL = "global"


class CameraMode(StrEnum):
    """How COLMAP's feature extraction assigns cameras to images."""

    SINGLE = "single"  # one camera for all images
    PER_IMAGE = "per_image"
    PER_FOLDER = "per_folder"
    AUTO = "auto"  # COLMAP's: by image size and EXIF


class PairCheckMode(StrEnum):
    """What the pair check does with a pair that the rest of the pair graph contradicts."""

    REMOVE = "remove"  # drop the pair's matches from the output database
    FLAG = "flag"  # keep it; only report it
