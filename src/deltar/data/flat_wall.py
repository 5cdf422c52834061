"""Synthetic flat-wall scenes: textured RGB-D frames of a plane at a known distance.

The camera looks at a wall ``distance_m`` metres away along its optical axis, optionally
rotated about the vertical axis; depth is the exact z-depth of the plane (metres). Used
by simulated recordings (``deltar record --simulate wall:1.5``) and the wall test
(:mod:`deltar.evaluation.wall_test`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from deltar.camera import CameraIntrinsics, pixel_rays
from deltar.data.rgbd import RGBDFrame

#: Prefix of flat-wall sources: ``wall:<metres>[:<frames>[:<height>x<width>]]``.
WALL_PREFIX = "wall:"


def flat_wall_frame(distance_m: float, height: int = 240, width: int = 320, *,
                    intrinsics: CameraIntrinsics | None = None, tilt_deg: float = 0.0,
                    seed: int = 0) -> RGBDFrame:
    """A synthetic RGB-D frame of a textured flat wall.

    Args:
        distance_m: distance of the wall along the optical axis at the image centre.
        height, width: image size in pixels.
        intrinsics: camera intrinsics (a 60-degree horizontal field of view when None).
        tilt_deg: rotation of the wall about the vertical axis, degrees.
        seed: seed of the texture.

    Returns:
        An :class:`~deltar.data.rgbd.RGBDFrame` with exact z-depth of the plane.
    """
    if not distance_m > 0:
        raise ValueError(f"distance_m must be > 0, got {distance_m}")
    if intrinsics is None:
        focal = width / (2 * np.tan(np.deg2rad(30.0)))
        intrinsics = CameraIntrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2,
                                      width, height)
    # Plane n . p = d with n tilted about y; depth along ray r = (x, y, 1): d / (n . r).
    tilt = np.deg2rad(tilt_deg)
    normal = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    rays_x = pixel_rays(intrinsics, height, width)[..., 0]
    denominator = normal[0] * rays_x + normal[2]
    offset = distance_m * normal[2]
    depth = np.where(denominator > 1e-6, offset / np.maximum(denominator, 1e-6), 0.0)
    rng = np.random.default_rng(seed)
    # Smooth random texture: blurred noise, upsampled.
    coarse = rng.uniform(60, 200, size=(max(2, height // 8), max(2, width // 8), 3))
    import cv2

    image = cv2.resize(coarse.astype(np.float32), (width, height),
                       interpolation=cv2.INTER_CUBIC)
    image = np.clip(image, 0, 255).astype(np.uint8)
    return RGBDFrame(image=image, depth_m=depth.astype(np.float32), intrinsics=intrinsics,
                     name=f"wall-{distance_m:g}m-{seed}")


class FlatWallSource(Sequence):
    """``frames`` flat-wall frames at one distance (texture seed = frame index)."""

    def __init__(self, distance_m: float, frames: int = 10, height: int = 240,
                 width: int = 320, tilt_deg: float = 0.0) -> None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        self.distance_m, self.frames = float(distance_m), int(frames)
        self.height, self.width, self.tilt_deg = int(height), int(width), float(tilt_deg)

    def __len__(self) -> int:
        return self.frames

    def __getitem__(self, index: int) -> RGBDFrame:  # type: ignore[override]
        if not 0 <= index < self.frames:
            raise IndexError(f"frame index {index} out of range for {self.frames} frames")
        return flat_wall_frame(self.distance_m, self.height, self.width,
                               tilt_deg=self.tilt_deg, seed=index)


def open_wall_source(spec: str) -> FlatWallSource:
    """A :class:`FlatWallSource` from ``wall:<metres>[:<frames>[:<height>x<width>]]``.

    Frames default to 10 and the size to 240x320 pixels.

    Raises:
        ValueError: the spec does not look like that; the message quotes it.
    """
    parts = spec[len(WALL_PREFIX):].split(":") if spec.startswith(WALL_PREFIX) else []
    try:
        distance = float(parts[0])
        frames = int(parts[1]) if len(parts) > 1 else 10
        height, width = (int(v) for v in parts[2].split("x")) if len(parts) > 2 \
            else (240, 320)
    except (ValueError, IndexError) as err:
        raise ValueError(f"wall source must look like 'wall:1.5', 'wall:1.5:20' or "
                         f"'wall:1.5:20:240x320', got {spec!r}") from err
    return FlatWallSource(distance, frames, height, width)
