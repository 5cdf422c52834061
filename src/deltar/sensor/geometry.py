"""Where each ToF zone falls in the camera image.

Frames: the *sensor frame* has x along the zone grid's columns (left to right), y along
its rows (top to bottom) and z along the viewing direction; the *camera frame* is the
usual pinhole frame (x right, y down, z forward). ``SensorExtrinsics`` maps sensor
coordinates to camera coordinates: ``p_cam = R @ p_sensor + t`` (metres).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from deltar.camera import CameraIntrinsics

#: DELTAR's sensor model: 45 x 45 degrees split evenly into the zone grid.
DEFAULT_FOV_DEG: tuple[float, float] = (45.0, 45.0)


@dataclass(frozen=True)
class SensorExtrinsics:
    """Rigid transform from the ToF sensor frame to the camera frame.

    Attributes:
        rotation: (3, 3) rotation matrix R with ``p_cam = R @ p_sensor + t``.
        translation_m: (3,) translation t in metres.
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation_m: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        for name in ("rotation", "translation_m"):
            kind = np.asarray(getattr(self, name)).dtype.kind
            if kind not in "iuf":
                raise ValueError(f"SensorExtrinsics.{name} must hold numbers, got values of "
                                 f"kind {kind!r} (strings, booleans or objects)")
        rot = np.asarray(self.rotation, dtype=np.float64)
        trans = np.asarray(self.translation_m, dtype=np.float64).reshape(-1)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise ValueError(f"SensorExtrinsics.rotation must be a finite 3x3 matrix, "
                             f"got shape {rot.shape}")
        rot = nearest_rotation(rot, "SensorExtrinsics.rotation")
        if trans.shape != (3,) or not np.all(np.isfinite(trans)):
            raise ValueError(f"SensorExtrinsics.translation_m must be 3 finite values, "
                             f"got {trans}")
        object.__setattr__(self, "rotation", rot)
        object.__setattr__(self, "translation_m", trans)

    def inverse(self) -> SensorExtrinsics:
        """The camera-to-sensor transform, as a ``SensorExtrinsics`` object."""
        rot_t = self.rotation.T
        return SensorExtrinsics(rot_t, -rot_t @ self.translation_m)


#: Largest |R^T R - I| (element-wise) and |det R - 1| of a matrix accepted as a rotation
#: (rotations written with four decimals are 5e-5 off); it is then made exact.
ROTATION_TOLERANCE = 1e-3


def nearest_rotation(matrix: np.ndarray, name: str = "matrix") -> np.ndarray:
    """A 3x3 matrix checked to be a rotation within :data:`ROTATION_TOLERANCE`, returned
    as the nearest exact rotation (by SVD) when it is off by rounding.

    Raises:
        ValueError: naming ``name``, with how far the matrix is from a rotation.
    """
    rot = np.asarray(matrix, dtype=np.float64)
    error = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if error > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise ValueError(f"{name} is not a rotation (|R^T R - I| = {error:.2g}, det = "
                         f"{det:.4f}; at most {ROTATION_TOLERANCE:g} off is accepted)")
    if error > 1e-9:
        left, _, right = np.linalg.svd(rot)
        rot = left @ right
    return rot


def zone_angles_deg(grid: int, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG) -> np.ndarray:
    """Angular bounds of each zone in the sensor frame.

    Args:
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) field of view in degrees, split evenly.

    Returns:
        (grid * grid, 4) float64 array of (ay0, ax0, ay1, ax1) in degrees, row-major,
        angles measured from the optical axis (negative = up / left).
    """
    if int(grid) != grid or grid < 1:
        raise ValueError(f"grid must be a positive integer, got {grid}")
    fov_x, fov_y = float(fov_deg[0]), float(fov_deg[1])
    if not (0 < fov_x < 180 and 0 < fov_y < 180):
        raise ValueError(f"fov_deg must be two angles in (0, 180) degrees, got {fov_deg}")
    edges_x = np.linspace(-fov_x / 2, fov_x / 2, grid + 1)
    edges_y = np.linspace(-fov_y / 2, fov_y / 2, grid + 1)
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    rows, cols = rows.reshape(-1), cols.reshape(-1)
    return np.stack([edges_y[rows], edges_x[cols], edges_y[rows + 1], edges_x[cols + 1]], axis=1)


def zone_rects(
    intrinsics: CameraIntrinsics,
    grid: int = 8,
    *,
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
    extrinsics: SensorExtrinsics | None = None,
    depth_m: float | np.ndarray = 2.0,
    samples_per_edge: int = 5,
) -> np.ndarray:
    """Each zone's bounding rectangle in image pixels.

    A zone is the set of rays between its angular bounds; the rectangle is the bounding
    box of its outline projected into the image at distance ``depth_m`` from the sensor
    (along the sensor's z axis). Parallax between sensor and camera makes the
    rectangle depend on that distance; with a zero translation it does not.

    Args:
        intrinsics: camera intrinsics (pixels).
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) sensor field of view in degrees.
        extrinsics: sensor-to-camera transform; identity when None.
        depth_m: scalar or (grid * grid,) per-zone distance in metres (> 0), e.g. each
            zone's measured mean.
        samples_per_edge: points projected along each zone edge (a rotated or tilted
            sensor maps zone edges to slanted lines).

    Returns:
        (grid * grid, 4) float32 array of (y0, x0, y1, x1) in pixels (pixel centres at
        integer coordinates, so the full image is (-0.5, -0.5, H - 0.5, W - 0.5)).
        Rectangles may extend past the image.
    """
    ext = extrinsics or SensorExtrinsics()
    zones = grid * grid
    depth = np.broadcast_to(np.asarray(depth_m, dtype=np.float64), (zones,)).copy()
    if not np.all(np.isfinite(depth)) or np.any(depth <= 0):
        raise ValueError("depth_m must be finite and > 0 for every zone")
    angles = np.deg2rad(zone_angles_deg(grid, fov_deg))  # (Z, 4): ay0 ax0 ay1 ax1
    t = np.linspace(0.0, 1.0, max(2, samples_per_edge))
    # Outline of each zone as (ax, ay) angle pairs: four edges, S samples each.
    ay0, ax0, ay1, ax1 = (angles[:, i : i + 1] for i in range(4))
    ax = np.concatenate([ax0 + (ax1 - ax0) * t, np.repeat(ax1, t.size, 1),
                         ax0 + (ax1 - ax0) * t, np.repeat(ax0, t.size, 1)], axis=1)
    ay = np.concatenate([np.repeat(ay0, t.size, 1), ay0 + (ay1 - ay0) * t,
                         np.repeat(ay1, t.size, 1), ay0 + (ay1 - ay0) * t], axis=1)
    points = np.stack([np.tan(ax), np.tan(ay), np.ones_like(ax)], axis=-1) * depth[:, None, None]
    cam = points @ ext.rotation.T + ext.translation_m  # (Z, P, 3)
    z = cam[..., 2]
    if np.any(z <= 1e-6):
        raise ValueError("some zone corners project behind the camera; check the extrinsics "
                         "and depth_m")
    u = intrinsics.fx * cam[..., 0] / z + intrinsics.cx
    v = intrinsics.fy * cam[..., 1] / z + intrinsics.cy
    return np.stack([v.min(1), u.min(1), v.max(1), u.max(1)], axis=1).astype(np.float32)


def zones_in_image(rects: np.ndarray, height: int, width: int) -> np.ndarray:
    """Which zone rectangles cover at least one pixel centre of a height x width image.

    Args:
        rects: (..., 4) rectangles (y0, x0, y1, x1) in pixels.
        height, width: image size in pixels.

    Returns:
        (...,) bool, False where a zone lies wholly outside the image (it carries no
        information about it).
    """
    bounds = zone_rects_to_pixel_bounds(rects, height, width)
    return (bounds[..., 2] > bounds[..., 0]) & (bounds[..., 3] > bounds[..., 1])


def check_zones_in_image(rects: np.ndarray, valid: np.ndarray, image_size: tuple[int, int],
                         source: str = "zones") -> None:
    """Refuse zones that all fall outside the image; warn when some valid ones do.

    Args:
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels.
        valid: (Z,) bool, the zones that carry a reading.
        image_size: (height, width) of the image, pixels.
        source: what the zones belong to, for the messages (e.g. ``"frames[0]"``).

    Raises:
        ValueError: valid zones exist but none covers a pixel of the image (a depth map
            from them would be constant): the calibration or rectangles are wrong.

    Warns:
        UserWarning: some valid zones lie outside the image, saying how many lie inside.
        Those outside are not dropped: a surface one reads may continue into the image.
    """
    valid = np.asarray(valid, dtype=bool).reshape(-1)
    inside = zones_in_image(rects, *image_size) & valid
    total = int(valid.sum())
    if total and not inside.any():
        raise ValueError(f"{source}: all {total} valid zones fall outside the "
                         f"{image_size[0]}x{image_size[1]} image; check the calibration "
                         "(extrinsics, intrinsics, fov_deg) or the zone rectangles")
    if int(inside.sum()) < total:
        warnings.warn(f"{source}: {total - int(inside.sum())} of {total} valid zones fall "
                      f"outside the {image_size[0]}x{image_size[1]} image "
                      f"({int(inside.sum())} inside); they are still read, and shape the "
                      "depth near the image's edge (check the calibration if none should)",
                      UserWarning, stacklevel=3)


def zone_rects_to_pixel_bounds(rects: np.ndarray, height: int, width: int) -> np.ndarray:
    """Integer pixel bounds (y0, x0, y1, x1) of the pixels a zone covers, clipped to the image.

    A pixel belongs to a zone when its centre lies in ``[y0, y1) x [x0, x1)``, so the
    bounds are ``ceil`` of the float rectangle; integer rectangles such as the 56 px
    simulation grid cover exactly 56 x 56 pixels and neighbouring zones never overlap.

    Args:
        rects: (..., 4) rectangles (y0, x0, y1, x1) in pixels.
        height, width: image size in pixels.

    Returns:
        (..., 4) int64, half-open, with 0 <= y0 <= y1 <= height and 0 <= x0 <= x1 <= width;
        a zone fully outside the image gets an empty range.
    """
    r = np.ceil(np.asarray(rects, dtype=np.float64))
    y0, y1 = np.clip(r[..., 0], 0, height), np.clip(r[..., 2], 0, height)
    x0, x1 = np.clip(r[..., 1], 0, width), np.clip(r[..., 3], 0, width)
    y1, x1 = np.maximum(y1, y0), np.maximum(x1, x0)
    return np.stack([y0, x0, y1, x1], axis=-1).astype(np.int64)


def mirror_zone_rects(rects: np.ndarray, width: int, grid: int) -> np.ndarray:
    """Zone rectangles of a left-right mirrored image, in row-major image order again.

    Zone ``(r, c)`` of the mirrored image is zone ``(r, grid - 1 - c)`` of the original,
    mirrored about the image centre: pixel column ``x`` goes to ``width - 1 - x``, so the
    columns ``[x0, x1)`` of a zone become ``[width - x1, width - x0)``.

    Args:
        rects: (grid * grid, 4) rectangles (y0, x0, y1, x1) in pixels.
        width: image width in pixels.
        grid: zones per side.

    Returns:
        (grid * grid, 4) float32 rectangles.
    """
    rects = np.asarray(rects, dtype=np.float32)
    if rects.shape != (grid * grid, 4):
        raise ValueError(f"rects must have shape ({grid * grid}, 4), got {rects.shape}")
    reordered = rects.reshape(grid, grid, 4)[:, ::-1].reshape(-1, 4)
    out = reordered.copy()
    out[:, 1] = width - reordered[:, 3]
    out[:, 3] = width - reordered[:, 1]
    return out
