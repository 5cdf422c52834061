"""Camera pose files: one 4x4 camera-to-world transform as four text rows.

A pose maps a point in the camera's optical frame (x right, y down, z forward) to the
world, ``p_world = T @ p_camera``, translations in metres. The layout of a recording's
``pose/<ns>.txt`` (docs/formats.md), of the shared TUM keyframes' ``pose/NNNNNN.txt``
and of 7-Scenes' ``frame-NNNNNN.pose.txt``. The one reader, writer and check of the
format, shared by ``deltar record`` (which carries an RGB-D folder's poses into its
recording) and ``deltar map`` (which reads them).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from deltar.io.atomic import write_text_atomic
from deltar.io.input_file import input_file, reading
from deltar.sensor.geometry import nearest_rotation

#: The pose folder of a recording (and of the shared TUM keyframes).
POSE_DIR = "pose"


def check_pose(pose: np.ndarray, source: str) -> np.ndarray:
    """Check one (4, 4) camera-to-world transform and return it as a float64 copy (a
    rotation block off by rounding made exact).

    Raises:
        ValueError: wrong shape, non-finite values, a last row other than (0, 0, 0, 1)
            or a rotation block that is not a rotation (orthonormal, det +1), naming
            ``source``.
    """
    matrix = np.array(pose, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f"{source}: a pose must be a 4x4 matrix, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{source}: the pose has NaN or infinite values")
    if not np.allclose(matrix[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise ValueError(f"{source}: the pose's last row must be 0 0 0 1, got {matrix[3]}")
    # Poses must be rigid camera-to-world transforms; rounding is made exact.
    matrix[:3, :3] = nearest_rotation(matrix[:3, :3], f"{source}: the pose's 3x3 block")
    return matrix


def read_pose_file(path: str | os.PathLike) -> np.ndarray:
    """One 4x4 camera-to-world text file (4 rows of 4 numbers), checked.

    Returns:
        (4, 4) float64 camera-to-world transform, metres.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not 16 numbers, or not a rigid transform (naming the file).
    """
    path = input_file(path, "pose file")
    with reading(path, "pose file"):
        try:
            with warnings.catch_warnings():
                # An empty file: the shape check below says so, naming the file.
                warnings.filterwarnings("ignore", message=".*input contained no data")
                values = np.loadtxt(path, dtype=np.float64, ndmin=2)
        except ValueError as err:
            raise ValueError(f"{path}: not a 4x4 matrix of numbers: {err}") from err
        return check_pose(values, str(path))


def write_pose_file(path: str | os.PathLike, pose: np.ndarray) -> Path:
    """Write one (4, 4) camera-to-world pose (metres) as 4 text rows, atomically.

    Raises:
        ValueError: not a rigid transform (:func:`check_pose`).
        FileExistsError: the file exists (a pose is never overwritten).
    """
    matrix = check_pose(pose, str(path))
    text = "\n".join(" ".join(f"{v:.9f}" for v in row) for row in matrix) + "\n"
    return write_text_atomic(path, text, overwrite=False)


def frame_pose_file(folder: str | os.PathLike, name: str) -> Path | None:
    """The pose file of the frame ``name`` of an RGB-D folder, or None.

    Looks for ``pose/<name>.txt`` (recordings, the shared TUM keyframes) and
    ``<name>.pose.txt`` (7-Scenes).
    """
    root = Path(folder)
    for candidate in (root / POSE_DIR / f"{name}.txt", root / f"{name}.pose.txt"):
        if candidate.is_file():
            return candidate
    return None
