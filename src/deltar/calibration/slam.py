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

from deltar.io.ply import read_ply, write_ply
from deltar.io.tum import read_tum_poses


def read_ply_points(path: str | os.PathLike) -> np.ndarray:
    """Vertex positions (N, 3) float64 of a PLY map (:func:`deltar.io.ply.read_ply`).

    Raises:
        FileNotFoundError: missing file.
        ValueError: not a readable PLY, or vertices that are NaN or infinite (a map's
            points are positions; such a file is damaged); the message names the file.
    """
    points = read_ply(path).points
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} of {len(points)} vertices are NaN or "
                         f"infinite (the first at index {int(np.argmax(bad))}); a map's "
                         "points must be finite positions in metres")
    return points


def write_ply_points(path: str | os.PathLike, points: np.ndarray, *, binary: bool = True,
                     overwrite: bool = False) -> Path:
    """Write (N, 3) points as a PLY file (binary little-endian float32, or ASCII), atomically."""
    return write_ply(path, np.asarray(points, dtype=np.float64).reshape(-1, 3), binary=binary,
                     overwrite=overwrite)


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
    """Read a TUM-format trajectory (``timestamp tx ty tz qx qy qz qw`` per line;
    :func:`deltar.io.tum.read_tum_poses`).

    Raises:
        FileNotFoundError: missing file.
        ValueError: malformed lines, non-unit quaternions, unsorted or duplicate
            timestamps (the message names the file and line).
    """
    return Trajectory(*read_tum_poses(path))


def world_to_camera(points_world: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """Map (N, 3) world points into the camera frame of a camera-to-world pose (4, 4)."""
    rot, trans = cam_to_world[:3, :3], cam_to_world[:3, 3]
    return (np.asarray(points_world, dtype=np.float64) - trans) @ rot
