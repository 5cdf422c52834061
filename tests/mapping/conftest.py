"""Tiny synthetic scenes for the mapping tests: a textured wall seen from known poses."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.camera import CameraIntrinsics

#: A small camera (60x80 pixels, ~67 deg horizontal field of view).
SMALL = CameraIntrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)
#: The wall: the world plane z = WALL_Z_M, seen by cameras looking along +z (not on a
#: voxel centre of the test grids: Open3D's point extraction skips exact zeros).
WALL_Z_M = 2.01


def pose_at(x_m: float, y_m: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world pose at (x, y, 0) looking along +z, turned by ``yaw_deg`` about y."""
    angle = np.deg2rad(yaw_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                    [-np.sin(angle), 0, np.cos(angle)]]
    pose[:3, 3] = (x_m, y_m, 0.0)
    return pose


def render_wall(pose: np.ndarray, intrinsics: CameraIntrinsics = SMALL,
                wall_z_m: float = WALL_Z_M) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) uint8, depth (H, W) metres) of the textured wall from ``pose``.

    The texture is a smooth colour pattern of the wall's world (x, y), so frames from
    different poses agree on it (odometry can track it).
    """
    v, u = np.mgrid[0:intrinsics.height, 0:intrinsics.width].astype(np.float64)
    rays = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                     np.ones_like(u)], axis=-1)
    world_rays = rays @ pose[:3, :3].T
    scale = (wall_z_m - pose[2, 3]) / world_rays[..., 2]  # depth along the optical axis
    hit = pose[:3, 3] + world_rays * scale[..., None]
    x, y = hit[..., 0], hit[..., 1]
    image = np.stack([128 + 100 * np.sin(7 * x) * np.cos(5 * y),
                      128 + 100 * np.cos(6 * x + 1) * np.sin(8 * y + 2),
                      128 + 90 * np.sin(4 * x + 9 * y)], axis=-1)
    return np.clip(image, 0, 255).astype(np.uint8), scale.astype(np.float32)


def write_wall_recording(folder, frames: int = 6):
    """A recording of the wall with poses in pose/ (the camera sliding 5 cm a frame)."""
    from deltar.mapping.scenes import write_posed_recording

    poses = [pose_at(0.05 * i) for i in range(frames)]
    return write_posed_recording(folder, [(*render_wall(p), p) for p in poses], SMALL)


@pytest.fixture
def wall_recording(tmp_path):
    """A 6-frame recording of the wall with its poses (:func:`write_wall_recording`)."""
    return write_wall_recording(tmp_path / "rec")
