"""External SLAM maps for calibration: a PLY point cloud and a TUM-format trajectory.

The trajectory gives the colour camera's pose (camera-to-world) over time, one line per
pose: ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, unit quaternion); lines
starting with ``#`` are comments. The cloud holds the map in the same world frame.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply_points(path: str | os.PathLike) -> np.ndarray:
    """Read the vertex positions of a PLY file (ASCII or binary little-endian).

    Only the ``vertex`` element's ``x``, ``y``, ``z`` are read; other vertex properties
    (colours, normals) are skipped. Elements after the vertices (faces) are ignored.

    Args:
        path: the ``.ply`` file.

    Returns:
        (N, 3) float64 points (the file's units, metres for SLAM maps).

    Raises:
        FileNotFoundError: missing file.
        ValueError: not a PLY, unsupported format (big-endian, list properties in the
            vertex element), no x/y/z, or truncated data; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            else:
                if words[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type {words[1]!r}")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
    if fmt not in ("ascii", "binary_little_endian"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r} (ascii or "
                         "binary_little_endian)")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: PLY has no vertex element")
    vertex_index = names.index("vertex")
    _, count, props = elements[vertex_index]
    prop_names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(prop_names):
        raise ValueError(f"{path}: vertex element has no x, y, z properties")
    if any(t == "list" for _, t in props):
        raise ValueError(f"{path}: list properties in the vertex element are not supported")
    if fmt == "ascii":
        lines = raw[body_start:].decode("ascii", errors="replace").splitlines()
        # Elements before the vertices take one line per item.
        skip = sum(e[1] for e in elements[:vertex_index])
        rows = lines[skip:skip + count]
        if len(rows) < count:
            raise ValueError(f"{path}: truncated PLY: {len(rows)} of {count} vertices")
        try:
            table = np.array([r.split()[:len(props)] for r in rows], dtype=np.float64)
        except ValueError as err:
            raise ValueError(f"{path}: malformed vertex line: {err}") from err
        if table.shape != (count, len(props)):
            raise ValueError(f"{path}: vertex lines must have {len(props)} values")
        cols = [prop_names.index(a) for a in "xyz"]
        return table[:, cols]
    offset = body_start
    for _, other_count, other_props in elements[:vertex_index]:
        if any(t == "list" for _, t in other_props):
            raise ValueError(f"{path}: list elements before the vertices are not supported")
        offset += other_count * np.dtype([(n, "<" + t) for n, t in other_props]).itemsize
    dtype = np.dtype([(n, "<" + t) for n, t in props])
    if len(raw) < offset + count * dtype.itemsize:
        raise ValueError(f"{path}: truncated PLY: expected {count} vertices of "
                         f"{dtype.itemsize} bytes")
    table = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
    return np.stack([table[a].astype(np.float64) for a in "xyz"], axis=1)


def write_ply_points(path: str | os.PathLike, points: np.ndarray, *, binary: bool = True,
                     overwrite: bool = False) -> Path:
    """Write (N, 3) points as a PLY file (binary little-endian float32, or ASCII), atomically."""
    from deltar.io.atomic import write_bytes_atomic

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    header = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\n"
              f"element vertex {pts.shape[0]}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n").encode("ascii")
    if binary:
        body = pts.astype("<f4").tobytes()
    else:
        body = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in pts).encode("ascii")
    return write_bytes_atomic(path, header + body, overwrite=overwrite)


@dataclass(frozen=True)
class Trajectory:
    """Camera poses over time (camera-to-world).

    Attributes:
        times_s: (N,) strictly increasing timestamps in seconds.
        poses: (N, 4, 4) camera-to-world transforms (metres).
    """

    times_s: np.ndarray
    poses: np.ndarray

    def pose_at(self, time_s: float, max_gap_s: float = 0.1) -> np.ndarray | None:
        """Camera-to-world pose at ``time_s``, interpolated (linear + slerp) between the
        two surrounding poses; None when the nearest pose on either side is more than
        ``max_gap_s`` away or ``time_s`` is outside the trajectory."""
        from scipy.spatial.transform import Rotation, Slerp

        times = self.times_s
        if times.size == 0 or time_s < times[0] - 1e-9 or time_s > times[-1] + 1e-9:
            return None
        right = int(np.clip(np.searchsorted(times, time_s), 1, max(times.size - 1, 1)))
        if times.size == 1:
            return self.poses[0].copy() if abs(times[0] - time_s) <= max_gap_s else None
        left = right - 1
        if time_s - times[left] > max_gap_s and times[right] - time_s > max_gap_s:
            return None
        if max(time_s - times[left], times[right] - time_s) > max_gap_s:
            nearest = left if time_s - times[left] <= times[right] - time_s else right
            return self.poses[nearest].copy()
        alpha = (time_s - times[left]) / (times[right] - times[left])
        rots = Rotation.from_matrix(self.poses[[left, right], :3, :3])
        pose = np.eye(4)
        pose[:3, :3] = Slerp([0.0, 1.0], rots)([alpha]).as_matrix()[0]
        pose[:3, 3] = (1 - alpha) * self.poses[left, :3, 3] + alpha * self.poses[right, :3, 3]
        return pose


def read_tum_trajectory(path: str | os.PathLike) -> Trajectory:
    """Read a TUM-format trajectory (``timestamp tx ty tz qx qy qz qw`` per line).

    Raises:
        FileNotFoundError: missing file.
        ValueError: malformed lines, non-unit quaternions, unsorted or duplicate
            timestamps (the message names the file and line).
    """
    from scipy.spatial.transform import Rotation

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    times, poses = [], []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values = np.array([float(v) for v in line.replace(",", " ").split()])
        except ValueError as err:
            raise ValueError(f"{path}:{number}: not numbers: {line!r}") from err
        if values.size != 8 or not np.all(np.isfinite(values)):
            raise ValueError(f"{path}:{number}: expected 8 finite values "
                             "(timestamp tx ty tz qx qy qz qw)")
        quat = values[4:]
        if abs(np.linalg.norm(quat) - 1) > 1e-3:
            raise ValueError(f"{path}:{number}: quaternion is not unit length")
        if times and values[0] <= times[-1]:
            raise ValueError(f"{path}:{number}: timestamps must increase strictly "
                             f"({values[0]} after {times[-1]})")
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat(quat).as_matrix()  # scipy order: x, y, z, w
        pose[:3, 3] = values[1:4]
        times.append(values[0])
        poses.append(pose)
    if not times:
        raise ValueError(f"{path}: trajectory has no poses")
    return Trajectory(np.array(times), np.stack(poses))


def world_to_camera(points_world: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """Map (N, 3) world points into the camera frame of a camera-to-world pose (4, 4)."""
    rot, trans = cam_to_world[:3, :3], cam_to_world[:3, 3]
    return (np.asarray(points_world, dtype=np.float64) - trans) @ rot
