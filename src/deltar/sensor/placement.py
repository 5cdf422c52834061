"""Nominal zone placement: where the zones fall in an image without a calibration;
and the raw sensor painted where its zones fall (:func:`zone_mean_depth`).

Without a :class:`~deltar.calibration.rig.RigCalibration` the zones are placed with
nominal intrinsics (the ZJU-L5 RealSense camera's, scaled to the image), the sensor's
nominal field of view and the identity sensor-to-camera pose. With the identity pose
there is no parallax, so the layout does not depend on the zone depths and is
computed once per image size, grid and geometry.
"""

from __future__ import annotations

import functools

import numpy as np

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics
from deltar.sensor.geometry import DEFAULT_FOV_DEG, zone_rects, zone_rects_to_pixel_bounds
from deltar.sensor.zone_frame import ZoneFrame


def nominal_zone_rects(frame: ZoneFrame, height: int, width: int,
                       intrinsics: CameraIntrinsics = ZJU_L5_INTRINSICS,
                       fov_deg: tuple[float, float] = DEFAULT_FOV_DEG) -> np.ndarray:
    """Zone rectangles without a calibration: nominal intrinsics, identity extrinsic.

    Args:
        frame: the zone frame (only its grid is used: no parallax).
        height, width: image size in pixels.
        intrinsics: nominal camera intrinsics, scaled to the image size.
        fov_deg: sensor field of view (horizontal, vertical) in degrees.

    Returns:
        (Z, 4) float32 rectangles (y0, x0, y1, x1) in image pixels, Z = grid * grid,
        row-major.

    Raises:
        ValueError: a non-positive image size.
    """
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    return _nominal_layout(intrinsics, frame.grid, tuple(fov_deg), int(height),
                           int(width)).copy()


@functools.lru_cache(maxsize=32)
def _nominal_layout(intrinsics: CameraIntrinsics, grid: int, fov_deg: tuple[float, float],
                    height: int, width: int) -> np.ndarray:
    return zone_rects(intrinsics.scaled(height, width), grid, fov_deg=fov_deg, depth_m=1.0)


def zone_mean_depth(frame: ZoneFrame, rects: np.ndarray, image_size: tuple[int, int]
                    ) -> np.ndarray:
    """The raw sensor as a depth map: each valid zone's mean painted over its pixels.

    Args:
        frame: the zone frame.
        rects: (Z, 4) zone rectangles in pixels (pixel centres in the half-open rectangle
            belong to the zone).
        image_size: (H, W).

    Returns:
        (H, W) float32 metres, 0 where no valid zone lies.
    """
    height, width = image_size
    out = np.zeros((height, width), dtype=np.float32)
    mean, _, valid = frame.flat()
    bounds = zone_rects_to_pixel_bounds(rects, height, width)
    for (y0, x0, y1, x1), value, ok in zip(bounds, mean, valid, strict=True):
        if ok:
            out[y0:y1, x0:x1] = value
    return out
