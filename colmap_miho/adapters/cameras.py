"""Camera intrinsics given by the user or a GT model, and the COLMAP cameras built from them
(pycolmap camera objects only: :mod:`.database` writes them into a database)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..errors import DatabaseError, InvalidInput


@dataclass(frozen=True, kw_only=True)
class CameraIntrinsics:
    """Intrinsics to write into a database camera: COLMAP ``model`` name, ``params`` in COLMAP's
    order and pixel convention (empty: keep the mean focal, centred principal point, no distortion),
    and the ``width``/``height`` they belong to (None: not checked)."""

    model: str
    params: tuple[float, ...] = ()
    width: int | None = None
    height: int | None = None

    def __post_init__(self) -> None:
        if (self.width is None) != (self.height is None):
            raise InvalidInput(f"camera intrinsics: give width and height together, got {self.width}x{self.height}")


def model_num_params(model: str) -> int:
    """Parameter count of the COLMAP camera ``model`` (any case); ValueError listing the known ones."""
    import pycolmap

    names = [n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"]
    if str(model).upper() not in names:
        raise InvalidInput(f"unknown camera model {model!r}; one of: {', '.join(names)}")
    return len(pycolmap.Camera.create_from_model_name(1, str(model).upper(), 1.0, 2, 2).params)


def camera_from(old: Any, intr: CameraIntrinsics) -> Any:
    """A new ``pycolmap.Camera`` with ``old``'s id, size and focal and ``intr``'s model and
    parameters (a prior focal). DatabaseError for another size, InvalidInput for a wrong parameter
    count."""
    import pycolmap

    if (intr.width is not None and intr.height is not None
            and (int(intr.width), int(intr.height)) != (int(old.width), int(old.height))):
        raise DatabaseError(f"camera {old.camera_id} is {old.width}x{old.height} px but the intrinsics given "
                            f"are for {intr.width}x{intr.height} px")
    model = str(intr.model).upper()
    new = pycolmap.Camera.create_from_model_name(int(old.camera_id), model, float(old.mean_focal_length()),
                                                 int(old.width), int(old.height))
    if intr.params:
        if len(intr.params) != len(new.params):
            raise InvalidInput(f"camera model {model} takes {len(new.params)} parameters, got {len(intr.params)}")
        new.params = [float(v) for v in intr.params]
        new.has_prior_focal_length = True
    else:
        new.has_prior_focal_length = bool(old.has_prior_focal_length)
    return new
