"""PLY point clouds: the one reader and the one writer of the package.

Read: ASCII or binary little-endian PLY files with a ``vertex`` element holding
``x``, ``y``, ``z`` (any numeric type) and optionally ``red``, ``green``, ``blue``;
other vertex properties (normals, ...) are skipped and elements after the vertices
(faces) are ignored. Write: binary little-endian (float32 positions) or ASCII, with
optional uchar colours and header comments, atomically.

Units are whatever the points are in: deltar writes metres in the camera frame
(x right, y down, z forward); SLAM maps are metres in their world frame.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from deltar.io.atomic import write_bytes_atomic
from deltar.io.input_file import input_file, reading

#: PLY scalar type names -> numpy type codes (without byte order).
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = ("ascii", "binary_little_endian")
_COLOURS = ("red", "green", "blue")


class PlyCloud(NamedTuple):
    """The contents of a PLY file (unpacks as ``points, colors, comments``).

    Attributes:
        points: (N, 3) float64 vertex positions (the file's units).
        colors: (N, 3) uint8 RGB colours, or None when the vertices have none.
        comments: the header's comment lines, without the ``comment`` keyword.
    """

    points: np.ndarray
    colors: np.ndarray | None
    comments: list[str]


def _parse_header(path: Path, raw: bytes):
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    newline = raw.find(b"\n", end)
    body_start = len(raw) if newline < 0 else newline + 1
    fmt, comments = None, []
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in raw[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "comment":
            comments.append(line.strip()[len("comment"):].strip())
            continue
        known = words[0] in ("format", "element", "property")
        if known and (len(words) < 3 or (words[0] == "element" and not words[2].isdigit())):
            raise ValueError(f"{path}: malformed PLY header line {line!r}")
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif words[1] not in PLY_TYPES:
                raise ValueError(f"{path}: unknown PLY property type {words[1]!r}")
            else:
                elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
    if fmt not in _FORMATS:
        raise ValueError(f"{path}: unsupported PLY format {fmt!r} (ascii or "
                         "binary_little_endian)")
    return fmt, comments, elements, body_start


def _vertex_table(path: Path, raw: bytes, fmt: str, elements, body_start: int):
    """The vertex element as a dict property name -> (N,) array."""
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: PLY has no vertex element")
    index = names.index("vertex")
    _, count, props = elements[index]
    prop_names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(prop_names):
        raise ValueError(f"{path}: vertex element has no x, y, z properties")
    if any(t == "list" for _, t in props):
        raise ValueError(f"{path}: list properties in the vertex element are not supported")
    if fmt == "ascii":
        lines = raw[body_start:].decode("ascii", errors="replace").splitlines()
        skip = sum(e[1] for e in elements[:index])  # one line per earlier item
        rows = lines[skip:skip + count]
        if len(rows) < count:
            raise ValueError(f"{path}: truncated PLY: {len(rows)} of {count} vertices")
        try:
            table = np.array([r.split()[:len(props)] for r in rows], dtype=np.float64)
        except ValueError as err:
            raise ValueError(f"{path}: malformed vertex line: {err}") from err
        if table.shape != (count, len(props)):
            raise ValueError(f"{path}: vertex lines must have {len(props)} values")
        return {name: table[:, i] for i, name in enumerate(prop_names)}
    offset = body_start
    for _, other_count, other_props in elements[:index]:
        if any(t == "list" for _, t in other_props):
            raise ValueError(f"{path}: list elements before the vertices are not supported")
        offset += other_count * np.dtype([(n, "<" + t) for n, t in other_props]).itemsize
    dtype = np.dtype([(n, "<" + t) for n, t in props])
    if len(raw) < offset + count * dtype.itemsize:
        raise ValueError(f"{path}: truncated PLY: expected {count} vertices of "
                         f"{dtype.itemsize} bytes")
    table = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
    return {name: table[name] for name in prop_names}


def read_ply(path: str | os.PathLike) -> PlyCloud:
    """Read the vertices of a PLY file (see the module docstring for what is supported).

    Args:
        path: the ``.ply`` file.

    Returns:
        :class:`PlyCloud`: (N, 3) float64 points, (N, 3) uint8 colours or None, comments.

    Raises:
        FileNotFoundError: missing file.
        ValueError: not a PLY, an unsupported format (big-endian, list properties in the
            vertex element), no x/y/z, or truncated data; the message names the file.
    """
    path = input_file(path, "PLY file")
    with reading(path, "PLY file"):
        raw = path.read_bytes()
        fmt, comments, elements, body_start = _parse_header(path, raw)
        table = _vertex_table(path, raw, fmt, elements, body_start)
        points = np.stack([np.asarray(table[a], dtype=np.float64) for a in "xyz"], axis=1)
        colors = None
        if all(c in table for c in _COLOURS):
            colors = np.stack([np.asarray(table[c]).astype(np.uint8) for c in _COLOURS],
                              axis=1)
        return PlyCloud(points, colors, comments)


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None,
              *, comments: Sequence[str] = (), binary: bool = True,
              overwrite: bool = False) -> Path:
    """Write points (and colours) as a PLY file, atomically.

    Args:
        path: the ``.ply`` file to write.
        points: (N, 3) positions, written as float32 (e.g. metres).
        colors: optional (N, 3) uint8 RGB colours (``red green blue`` uchar properties).
        comments: header comments, one line each (newlines are folded to spaces).
        binary: binary little-endian (default) or ASCII (positions with 6 decimals).
        overwrite: replace an existing file (default: ``FileExistsError``).

    Returns:
        The written path.

    Raises:
        ValueError: points not (N, 3), or colours not of the same shape.
    """
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {pts.shape}")
    cols = None if colors is None else np.asarray(colors, dtype=np.uint8)
    if cols is not None and cols.shape != pts.shape:
        raise ValueError(f"colors must be (N, 3) like points {pts.shape}, got {cols.shape}")
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    header += [f"comment {' '.join(str(c).split())}" for c in comments]
    header += [f"element vertex {pts.shape[0]}", "property float x", "property float y",
               "property float z"]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cols is not None:
        header += [f"property uchar {c}" for c in _COLOURS]
        fields += [(c, "u1") for c in _COLOURS]
    header.append("end_header")
    rows = np.empty(pts.shape[0], dtype=np.dtype(fields))
    for i, axis in enumerate("xyz"):
        rows[axis] = pts[:, i]
    if cols is not None:
        for i, colour in enumerate(_COLOURS):
            rows[colour] = cols[:, i]
    if binary:
        body = rows.tobytes()
    else:
        text = np.char.mod("%.6f", np.asarray(points, dtype=np.float64))
        if cols is not None:
            text = np.concatenate([text, cols.astype(str)], axis=1)
        body = "".join(" ".join(row) + "\n" for row in text.tolist()).encode("ascii")
    data = ("\n".join(header) + "\n").encode("ascii") + body
    return write_bytes_atomic(path, data, overwrite=overwrite)
