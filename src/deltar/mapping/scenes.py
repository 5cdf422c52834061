"""Recordings with known poses from RGB-D frames, with simulated L5 zones.

:func:`write_posed_recording` writes what ``deltar record --simulate`` writes (colour,
reference depth, simulated zone frames) plus the recording's ``pose/<ns>.txt`` camera
poses, so ``deltar map`` can be run and scored on any RGB-D scene with ground-truth
poses (benchmarks/bench_map.py does so on the shared TUM and 7-Scenes scenes).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.io.atomic import write_text_atomic
from deltar.mapping.builder import POSE_DIR
from deltar.mapping.poses import check_pose, read_pose_file


def write_pose_file(path: str | os.PathLike, pose: np.ndarray) -> Path:
    """Write one (4, 4) camera-to-world pose as 4 text rows, atomically (never overwrites)."""
    matrix = check_pose(pose, str(path))
    text = "\n".join(" ".join(f"{v:.9f}" for v in row) for row in matrix) + "\n"
    return write_text_atomic(path, text, overwrite=False)


def scene_poses(folder: str | os.PathLike, names: list[str]) -> np.ndarray:
    """(N, 4, 4) poses of the named frames of a shared RGB-D scene folder.

    Looks for ``pose/<name>.txt`` (the TUM keyframes' layout) and
    ``<name>.pose.txt`` (7-Scenes).

    Raises:
        FileNotFoundError: a frame without a pose file.
    """
    root = Path(folder)
    poses = []
    for name in names:
        for candidate in (root / "pose" / f"{name}.txt", root / f"{name}.pose.txt"):
            if candidate.is_file():
                poses.append(read_pose_file(candidate))
                break
        else:
            raise FileNotFoundError(f"{root}: no pose file for frame {name}")
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
    from deltar.io.recording import RecordingMeta, RecordingWriter, timestamp_to_ns
    from deltar.sensor.geometry import zone_rects
    from deltar.sensor.simulate_frame import simulate_zone_frame
    from deltar.sensor.zone_frame import ZoneFrame

    folder = Path(out)
    writer = RecordingWriter(folder, RecordingMeta(intrinsics, sensor_model=sensor_model,
                                                   grid=grid))
    rects = zone_rects(intrinsics, grid)
    (folder / POSE_DIR).mkdir(exist_ok=True)
    for index, (image, depth, pose) in enumerate(frames):
        time_s = index * frame_period_s
        writer.add_color(time_s, image)
        writer.add_depth(time_s, np.where(np.isfinite(depth), depth, 0.0))
        zones = simulate_zone_frame(np.asarray(depth, dtype=np.float32), rects)
        writer.add_zone_frame(ZoneFrame(mean_m=zones.mean_m, sigma_m=zones.sigma_m,
                                        valid=zones.valid, no_target=zones.no_target,
                                        timestamp_s=time_s + 0.001,
                                        sensor_model=sensor_model))
        write_pose_file(folder / POSE_DIR / f"{timestamp_to_ns(time_s)}.txt", pose)
    writer.close()
    return folder
