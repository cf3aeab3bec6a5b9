"""Closed choices used across colmap-miho (pure Python, cheap to import)."""

from __future__ import annotations

from enum import Enum
from typing import TypeVar

from .errors import InvalidInput

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
            raise InvalidInput(f"{name}={value!r} is not one of: {choices}") from None

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


class Sampling(StrEnum):
    """How the filter's RANSAC draws minimal samples."""

    LOCAL = "local"  # NAPSAC-style: a share of the samples around a seed match
    UNIFORM = "uniform"  # the paper's


class MihoThreshold(StrEnum):
    """What MiHo's thresholds t_l and t_h bound."""

    HALF = "half"  # each half-match's transfer errors (paper, reference)
    FULL = "full"  # the full match: twice the largest half-match error
    FULL_SEARCH = "full_search"  # full match while MOP searches, half-matches at keep time


class Assignment(StrEnum):
    """Rule giving each kept match one homography (paper App. A.4)."""

    PAPER = "paper"
    MEDIAN = "median"
    REFERENCE = "reference"


class Perturbations(StrEnum):
    """Template shape sets of the NCC refinement (paper App. E, A_{rho,f})."""

    NONE = "none"  # the patch homography pair itself (K = 1)
    SMALL = "small"  # identity, rotations by +-15 degrees, factors 5/6 and 6/5 (K = 5)
    PAPER = "paper"  # 5 rotations x 5 factors of the paper (K = 25)


class Rectification(StrEnum):
    """Patch homography pairs the track walk searches each match with."""

    FILTER = "filter"  # the filter's plane of the match
    LOCAL = "local"  # a local affine fit to the nearest matches of its cluster
    BOTH = "both"  # both pairs; the higher NCC peak wins


class RunnerKind(StrEnum):
    """Where a run's parallel work runs (the summary's ``runner``)."""

    INLINE = "inline"  # in this process
    PROCESSES = "processes"  # a local process pool
    DASK = "dask"  # a Dask cluster, local or remote


class MatchCheckMode(StrEnum):
    """What the match check (verification against a global estimate of the cameras) does."""

    OFF = "off"  # no global estimate, nothing judged
    REMOVE = "remove"  # drop the matches (and pairs) the trusted estimate contradicts
    FLAG = "flag"  # judge and report, remove nothing
