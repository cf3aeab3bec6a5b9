"""A binary little-endian PLY reader and writer (the layout COLMAP writes), to check the
package's PLY export."""

from __future__ import annotations

from pathlib import Path

import numpy as np

_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "short": "<i2", "ushort": "<u2", "int": "<i4", "int32": "<i4",
              "uint": "<u4", "uint32": "<u4"}


def write_ply(points: np.ndarray, path: str | Path, colors: np.ndarray | None = None) -> Path:
    """Write (N, 3) points (as float32) and optional (N, 3) uint8 colours; returns the path."""
    p = np.asarray(points, np.float64)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(p), dtype=fields)
    rows["x"], rows["y"], rows["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colors is not None:
        c = np.asarray(colors)
        rows["red"], rows["green"], rows["blue"] = c[:, 0], c[:, 1], c[:, 2]
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in fields)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(p)}\n{props}end_header\n"
    path = Path(path)
    path.write_bytes(header.encode("ascii") + rows.tobytes())
    return path


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The vertices of a binary little-endian PLY: (N, 3) float64 xyz and (N, 3) uint8 RGB or
    None. Other vertex properties are skipped; other formats and elements before the vertices
    raise ``ValueError``."""
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        fields: list[tuple[str, str]] = []
        count = None
        in_vertex = False
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header without end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format" and words[1] != "binary_little_endian":
                raise ValueError(f"{path}: PLY format {words[1]} not supported")
            if words[0] == "element":
                if words[1] == "vertex":
                    count, in_vertex = int(words[2]), True
                elif count is None:
                    raise ValueError(f"{path}: PLY element {words[1]!r} before the vertices")
                else:
                    in_vertex = False
            elif words[0] == "property" and in_vertex:
                if words[1] == "list" or words[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: vertex property {' '.join(words[1:])!r} not supported")
                fields.append((words[2], _PLY_TYPES[words[1]]))
            elif words[0] == "end_header":
                break
        if count is None or not {"x", "y", "z"} <= {n for n, _ in fields}:
            raise ValueError(f"{path}: no vertex element with x, y, z")
        rows = np.frombuffer(f.read(np.dtype(fields).itemsize * count), dtype=fields, count=count)
    xyz = np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float64)
    rgb = None
    if {"red", "green", "blue"} <= {n for n, _ in fields}:
        rgb = np.stack([rows["red"], rows["green"], rows["blue"]], axis=1).astype(np.uint8)
    return xyz, rgb
