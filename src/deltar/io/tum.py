"""TUM RGB-D trajectory files: one pose per line, ``t tx ty tz qx qy qz qw``.

``t`` is seconds, the translation metres and the unit quaternion (x, y, z, w) the
camera-to-world rotation; ``#`` starts a comment. The one reader of the format, shared
by the calibration against a SLAM map (:mod:`deltar.calibration.slam`) and the mapping
(:mod:`deltar.mapping.poses`), which wrap its arrays in their trajectory types.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deltar.io.input_file import input_file, reading
from deltar.sensor.geometry import ROTATION_TOLERANCE


def quaternion_pose(translation: np.ndarray, quaternion_xyzw: np.ndarray,
                    source: str) -> np.ndarray:
    """(4, 4) transform from a translation (3,) in metres and a unit quaternion (x, y, z, w).

    Raises:
        ValueError: non-finite values or a quaternion whose norm is not 1 (+-1e-3),
            naming ``source``.
    """
    from scipy.spatial.transform import Rotation

    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise ValueError(f"{source}: the pose has NaN or infinite values")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > ROTATION_TOLERANCE:
        raise ValueError(f"{source}: the quaternion's norm is {norm:.4f}, not 1: not a "
                         "rotation")
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    pose[:3, 3] = t
    return pose


def read_tum_poses(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The poses of a TUM trajectory file.

    Returns:
        ``(times_s, poses)``: (N,) float64 strictly increasing times in seconds and
        (N, 4, 4) float64 camera-to-world transforms in metres.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a line that is not 8 numbers, a quaternion that is not unit length,
            times not strictly increasing, or no pose (naming the file and line).
    """
    path = input_file(path, "trajectory file")
    with reading(path, "trajectory file"):
        return _parse(path)


def _parse(path: Path) -> tuple[np.ndarray, np.ndarray]:
    times, poses = [], []
    for number, line in enumerate(path.read_bytes().decode("utf-8").splitlines(), start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        where = f"{path}:{number}"
        try:
            values = [float(v) for v in text.replace(",", " ").split()]
        except ValueError as err:
            raise ValueError(f"{where}: expected 't tx ty tz qx qy qz qw', got {text!r}") \
                from err
        if len(values) != 8:
            raise ValueError(f"{where}: expected 8 numbers 't tx ty tz qx qy qz qw', got "
                             f"{len(values)}")
        if not np.isfinite(values[0]):
            raise ValueError(f"{where}: the time is not a finite number")
        if times and values[0] <= times[-1]:
            raise ValueError(f"{where}: time {values[0]} is not after the previous "
                             f"{times[-1]}")
        times.append(values[0])
        poses.append(quaternion_pose(np.array(values[1:4]), np.array(values[4:8]), where))
    if not poses:
        raise ValueError(f"{path}: no pose lines ('t tx ty tz qx qy qz qw')")
    return np.array(times), np.stack(poses)
