"""The COLMAP model files (:data:`MODEL_STEMS`) and a check of a binary model before pycolmap reads
it: pycolmap trusts every count in the file, so a damaged one allocates without bound or aborts.
:func:`check_binary_model` walks the records with each count checked against the bytes left."""

from __future__ import annotations

import functools
import os
import struct
from pathlib import Path

from ..errors import InvalidInput

#: The files of a COLMAP model (``<stem>.bin`` or ``<stem>.txt``), in COLMAP's order.
MODEL_STEMS = ("cameras", "images", "points3D", "rigs", "frames")
#: The extensions of the two model formats, binary and text.
MODEL_EXTENSIONS = (".bin", ".txt")

_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
#: Fixed parts of the records, bytes.
_CAMERA_HEAD = 4 + 4 + 8 + 8  # camera_id, model_id, width, height
_IMAGE_HEAD = 4 + 7 * 8 + 4  # image_id, cam_from_world (quaternion + translation), camera_id
_POINT2D = 8 + 8 + 8  # x, y, point3D_id
_POINT3D_HEAD = 8 + 3 * 8 + 3 + 8 + 8  # point3D_id, xyz, rgb, error, track length
_TRACK_ELEMENT = 4 + 4  # image_id, point2D_idx
_RIG_HEAD = 4 + 4  # rig_id, number of sensors
_SENSOR = 4 + 4  # sensor type, sensor id
_FRAME_HEAD = 4 + 4 + 7 * 8 + 4  # frame_id, rig_id, rig_from_world, number of data ids
_DATA_ID = 4 + 4 + 8  # sensor type, sensor id, data id


class _Damaged(Exception):
    """A count or a record that does not fit the file."""


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.pos = memoryview(data), 0

    def left(self) -> int:
        return len(self.data) - self.pos

    def skip(self, size: int, what: str) -> None:
        if size > self.left():
            raise _Damaged(f"{what} needs {size} bytes at offset {self.pos}, {self.left()} left")
        self.pos += size

    def u64(self, what: str) -> int:
        self.skip(8, what)
        return _U64.unpack_from(self.data, self.pos - 8)[0]

    def u32(self, what: str) -> int:
        self.skip(4, what)
        return _U32.unpack_from(self.data, self.pos - 4)[0]

    def count(self, what: str, record: int) -> int:
        """A uint64 count of records of at least ``record`` bytes, refused if they cannot fit."""
        n = self.u64(what)
        if n * record > self.left():
            raise _Damaged(f"{what} is {n}, but {n} records need at least {n * record} bytes and "
                           f"{self.left()} are left")
        return n

    def name(self) -> None:
        end = bytes(self.data[self.pos:]).find(b"\0") if self.left() < 4096 else \
            bytes(self.data[self.pos:self.pos + 4096]).find(b"\0")
        if end < 0:
            raise _Damaged(f"image name at offset {self.pos} has no end")
        self.pos += end + 1


@functools.cache
def _num_params(model_id: int) -> int:
    import pycolmap

    try:
        model = pycolmap.CameraModelId(model_id)
    except ValueError:
        raise _Damaged(f"unknown camera model id {model_id}") from None
    if model == pycolmap.CameraModelId.INVALID:
        raise _Damaged(f"invalid camera model id {model_id}")
    return len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)


def _cameras(r: _Reader) -> None:
    for _ in range(r.count("the number of cameras", _CAMERA_HEAD)):
        r.skip(4, "a camera id")
        r.skip(4, "a camera model id")
        model_id = struct.unpack_from("<i", r.data, r.pos - 4)[0]
        r.skip(16, "a camera size")
        r.skip(8 * _num_params(model_id), "camera parameters")


def _images(r: _Reader) -> None:
    for _ in range(r.count("the number of images", _IMAGE_HEAD + 1 + 8)):
        r.skip(_IMAGE_HEAD, "an image record")
        r.name()
        r.skip(_POINT2D * r.count("an image's number of 2D points", _POINT2D), "2D points")


def _points3d(r: _Reader) -> None:
    for _ in range(r.count("the number of 3D points", _POINT3D_HEAD)):
        r.skip(_POINT3D_HEAD - 8, "a 3D point")
        r.skip(_TRACK_ELEMENT * r.count("a track length", _TRACK_ELEMENT), "a track")


def _rigs(r: _Reader) -> None:
    for _ in range(r.count("the number of rigs", _RIG_HEAD)):
        r.skip(4, "a rig id")
        sensors = r.u32("a rig's number of sensors")
        if sensors * _SENSOR > r.left():
            raise _Damaged(f"a rig's number of sensors is {sensors}, more than the {r.left()} bytes left hold")
        if sensors:
            r.skip(_SENSOR, "a reference sensor")
        for _ in range(max(0, sensors - 1)):
            r.skip(_SENSOR, "a sensor")
            r.skip(1, "a sensor's pose flag")
            if r.data[r.pos - 1]:
                r.skip(7 * 8, "a sensor pose")


def _frames(r: _Reader) -> None:
    for _ in range(r.count("the number of frames", _FRAME_HEAD)):
        r.skip(_FRAME_HEAD - 4, "a frame record")
        n = r.u32("a frame's number of data ids")
        r.skip(n * _DATA_ID, "a frame's data ids")


#: The binary model files and their walkers.
_WALKERS = {"cameras.bin": _cameras, "images.bin": _images, "points3D.bin": _points3d,
            "rigs.bin": _rigs, "frames.bin": _frames}


def check_binary_model(folder: str | os.PathLike) -> None:
    """Walk every binary model file in ``folder`` with each count checked against the bytes left;
    InvalidInput naming a truncated or damaged file. Text models and missing files pass."""
    for name, walk in _WALKERS.items():
        path = Path(folder) / name
        if not path.is_file():
            continue
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InvalidInput(f"cannot read the COLMAP model file {path}: {exc.strerror or exc}") from None
        reader = _Reader(data)
        try:
            walk(reader)
        except _Damaged as exc:
            raise InvalidInput(f"COLMAP model file {path} is truncated or damaged ({exc}); write it again") from None
        if reader.left():
            raise InvalidInput(f"COLMAP model file {path} is damaged ({reader.left()} bytes after its last "
                               "record); write it again")
