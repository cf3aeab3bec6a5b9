"""A damaged binary COLMAP model is one line naming its file, before pycolmap reads it.

pycolmap's reader trusts the counts in the file: a truncated file made it allocate without
bound. Every count is now checked against the bytes left.
"""

from __future__ import annotations

import struct
import time

import pytest

from colmap_miho.adapters.model_files import check_binary_model
from colmap_miho.cli import main
from colmap_miho.errors import InvalidInput


def test_a_whole_model_passes(model):
    check_binary_model(model)


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin", "frames.bin", "rigs.bin"])
@pytest.mark.parametrize("keep", [0.2, 0.5, 0.9, 0.999])
def test_every_truncation_is_refused_naming_the_file(name, keep, model):
    data = (model / name).read_bytes()
    (model / name).write_bytes(data[: max(1, int(len(data) * keep))])
    with pytest.raises(InvalidInput, match=rf"COLMAP model file .*{name} is truncated or damaged"):
        check_binary_model(model)


def test_trailing_bytes_are_refused(model):
    with open(model / "points3D.bin", "ab") as fh:
        fh.write(b"\0" * 5)
    with pytest.raises(InvalidInput, match="points3D.bin is damaged .5 bytes after"):
        check_binary_model(model)


def _first_track_length_offset(data: bytes) -> int:
    return 8 + 8 + 24 + 3 + 8  # count, then the first point's id, xyz, rgb, error


@pytest.mark.parametrize("where", ["points_count", "track_length", "points2D_count"])
def test_a_lying_count_is_refused_at_once(where, model):
    name = "images.bin" if where == "points2D_count" else "points3D.bin"
    data = bytearray((model / name).read_bytes())
    if where == "points_count":
        offset = 0
    elif where == "track_length":
        offset = _first_track_length_offset(bytes(data))
    else:
        offset = 8 + 4 + 56 + 4 + bytes(data[8 + 4 + 56 + 4:]).index(b"\0") + 1
    struct.pack_into("<Q", data, offset, 1 << 60)
    (model / name).write_bytes(bytes(data))
    start = time.perf_counter()
    with pytest.raises(InvalidInput, match=rf"{name} is truncated or damaged .* is {1 << 60}"):
        check_binary_model(model)
    assert time.perf_counter() - start < 1.0


@pytest.mark.parametrize("option", ["--model", "--gt"])
def test_report_names_the_damaged_file_and_exits_2(option, model, scene, tmp_path, capfd):
    data = bytearray((model / "points3D.bin").read_bytes())
    struct.pack_into("<Q", data, _first_track_length_offset(bytes(data)), 1 << 40)
    (model / "points3D.bin").write_bytes(bytes(data))
    good = tmp_path / "good"
    good.mkdir()
    scene.gt_reconstruction.write(str(good))
    argv = ["report", "--model", str(model), "-q"] if option == "--model" else \
        ["report", "--model", str(good), "--gt", str(model), "-q"]
    capfd.readouterr()
    assert main(argv) == 2
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and str(model / "points3D.bin") in lines[0], lines
