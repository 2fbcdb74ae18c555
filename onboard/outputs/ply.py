"""Coloured point clouds as binary little-endian PLY.

One numpy structured array per file: no per-point Python, so millions of points
write and read in well under a second.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

_VERTEX_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)

_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4",
    "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4",
    "double": "<f8", "float64": "<f8",
}


def write_ply(path: Path | str, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Write points `xyz` (N,3, stored as float32) with colours `rgb` (N,3 uint8).

    Written to a temp file in the same directory then renamed, so a reader (the
    ground-side listener) sees either the old file or the complete new one.
    """
    xyz = np.asarray(xyz)
    rgb = np.asarray(rgb)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"need xyz (N,3) and rgb (N,3), got {xyz.shape} and {rgb.shape}")
    if rgb.dtype != np.uint8:
        # Refuse rather than cast: float 0..1 colours would silently become black.
        raise ValueError(f"rgb must be uint8, got {rgb.dtype}")
    vertices = np.empty(len(xyz), dtype=_VERTEX_DTYPE)
    vertices["x"], vertices["y"], vertices["z"] = (xyz[:, k].astype(np.float32) for k in range(3))
    vertices["red"], vertices["green"], vertices["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = (
        "ply\n"
        "format binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n"
    ).encode("ascii")

    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(header)
            f.write(vertices.tobytes())
            f.flush()
            # Durable before the rename, or a power cut can leave an empty file
            # under the final name.
            os.fsync(f.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    logger.debug("wrote %d points to %s", len(vertices), path)


def _parse_header(f) -> tuple[int, np.dtype]:
    """Read the header up to `end_header`; returns (vertex count, vertex dtype).

    Only files whose first element is `vertex` with scalar properties are
    supported (what we write, and what most point-cloud tools write).
    """
    if f.readline().strip() != b"ply":
        raise ValueError("not a PLY file")
    n_vertices = -1
    fields: list[tuple[str, str]] = []
    element = None
    fmt = None
    for raw in f:
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            element = words[1]
            if element == "vertex":
                n_vertices = int(words[2])
            elif n_vertices < 0:
                raise ValueError("PLY elements before 'vertex' are not supported")
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list":
                raise ValueError("list properties on vertices are not supported")
            if words[1] not in _PLY_TYPES:
                raise ValueError(f"unknown PLY property type {words[1]!r}")
            fields.append((words[2], _PLY_TYPES[words[1]]))
    else:
        raise ValueError("PLY header has no end_header")
    if fmt != "binary_little_endian":
        raise ValueError(f"unsupported PLY format {fmt!r} (only binary_little_endian)")
    if n_vertices < 0:
        raise ValueError("PLY has no vertex element")
    return n_vertices, np.dtype(fields)


def read_ply(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Read (xyz float32 (N,3), rgb uint8 (N,3)); missing colours read as 0."""
    with open(path, "rb") as f:
        n, dtype = _parse_header(f)
        # Read bytes rather than np.fromfile: the header was consumed through
        # Python's buffered reader, whose position the raw fd does not share.
        data = f.read(n * dtype.itemsize)
    vertices = np.frombuffer(data, dtype=dtype, count=len(data) // dtype.itemsize)
    if len(vertices) != n:
        raise ValueError(f"PLY truncated: header says {n} vertices, found {len(vertices)}")
    names = dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise ValueError("PLY vertices lack x/y/z")
    xyz = np.stack([vertices[k].astype(np.float32) for k in ("x", "y", "z")], axis=1)
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([vertices[k].astype(np.uint8) for k in ("red", "green", "blue")], axis=1)
    else:
        rgb = np.zeros((n, 3), dtype=np.uint8)
    return xyz, rgb
