"""Recordings with known poses from RGB-D frames, with simulated L5 zones.

:func:`write_posed_recording` writes a recording (colour, reference depth, simulated
zone frames and ``pose/<ns>.txt`` camera poses) with one zone frame per image, placed
with the nominal geometry: the recordings on which benchmarks/bench_map.py runs and
scores ``deltar map`` (the shared TUM and 7-Scenes scenes). ``deltar record --simulate``
writes the same items from any RGB-D folder with pose files, at the sensor's own rate.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.io.pose_file import frame_pose_file, read_pose_file


def scene_poses(folder: str | os.PathLike, names: list[str]) -> np.ndarray:
    """(N, 4, 4) poses of the named frames of a shared RGB-D scene folder.

    Looks for ``pose/<name>.txt`` (the TUM keyframes' layout) and
    ``<name>.pose.txt`` (7-Scenes).

    Raises:
        FileNotFoundError: a frame without a pose file.
    """
    poses = []
    for name in names:
        path = frame_pose_file(folder, name)
        if path is None:
            raise FileNotFoundError(f"{folder}: no pose file for frame {name}")
        poses.append(read_pose_file(path))
    return np.stack(poses)


def write_posed_recording(out: str | os.PathLike,
                          frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
                          intrinsics: CameraIntrinsics, *, grid: int = 8,
                          frame_period_s: float = 1 / 30,
                          sensor_model: str = "VL53L5CX") -> Path:
    """Write a recording folder with simulated zones and per-frame poses.

    Args:
        out: the new recording folder.
        frames: (image (H, W, 3) uint8 RGB, depth (H, W) metres 0 = invalid,
            camera-to-world (4, 4) pose) per frame.
        intrinsics: the camera's intrinsics at (H, W).
        grid: zones per side.
        frame_period_s: seconds between frames (frame i is at ``i * frame_period_s``,
            its zone frame 1 ms later).
        sensor_model: the sensor model written to meta.json (its range caps the map).

    Returns:
        The recording folder.
    """
    from deltar.io.recording import RecordingMeta, RecordingWriter
    from deltar.sensor.geometry import zone_rects
    from deltar.sensor.simulate_frame import simulate_zone_frame
    from deltar.sensor.zone_frame import ZoneFrame

    folder = Path(out)
    writer = RecordingWriter(folder, RecordingMeta(intrinsics, sensor_model=sensor_model,
                                                   grid=grid))
    rects = zone_rects(intrinsics, grid)
    for index, (image, depth, pose) in enumerate(frames):
        time_s = index * frame_period_s
        writer.add_color(time_s, image)
        writer.add_depth(time_s, np.where(np.isfinite(depth), depth, 0.0))
        zones = simulate_zone_frame(np.asarray(depth, dtype=np.float32), rects)
        writer.add_zone_frame(ZoneFrame(mean_m=zones.mean_m, sigma_m=zones.sigma_m,
                                        valid=zones.valid, no_target=zones.no_target,
                                        timestamp_s=time_s + 0.001,
                                        sensor_model=sensor_model))
        writer.add_pose(time_s, pose)
    writer.close()
    return folder
