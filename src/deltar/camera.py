"""The colour camera: its images, pinhole intrinsics and depth back-projection.

A leaf module (it imports nothing of deltar's own), so every package can use it.
Conventions: pixel centres sit at integer coordinates (``u`` = column, ``v`` = row);
the camera frame is x right, y down, z forward; depth is z-depth (along the optical
axis) in metres, and 0 marks an invalid pixel.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the colour camera, in pixels.

    Attributes:
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (pixel centres at integer coordinates).
        width, height: image size in pixels the intrinsics refer to.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = strict_number(getattr(self, name), f"CameraIntrinsics.{name}")
            if not math.isfinite(value):
                raise ValueError(f"CameraIntrinsics.{name} must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"CameraIntrinsics focal lengths must be > 0, got fx={self.fx}, "
                             f"fy={self.fy}")
        for name in ("width", "height"):
            strict_integer(getattr(self, name), f"CameraIntrinsics.{name}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"CameraIntrinsics size must be positive, got "
                             f"{self.width}x{self.height}")

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 matrix K (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, height: int, width: int) -> CameraIntrinsics:
        """Intrinsics for the same camera with the image resized to ``height`` x ``width``."""
        sx, sy = width / self.width, height / self.height
        # Pixel centres sit at integer coordinates, so the principal point scales about -0.5.
        return CameraIntrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                                (self.cy + 0.5) * sy - 0.5, int(width), int(height))

    def cropped(self, top: int, left: int, height: int, width: int) -> CameraIntrinsics:
        """Intrinsics of the crop starting at pixel (``top``, ``left``) of size height x width."""
        return CameraIntrinsics(self.fx, self.fy, self.cx - left, self.cy - top,
                                int(width), int(height))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> CameraIntrinsics:
        """Build from ``{"fx", "fy", "cx", "cy"}`` (pixels) and ``{"width", "height"}``
        (whole pixels); strings, booleans and fractional sizes are refused.

        Raises:
            ValueError: naming the key.
        """
        if not isinstance(data, dict):
            raise ValueError(f"camera intrinsics must be an object, got {type(data).__name__}")
        missing = {"fx", "fy", "cx", "cy", "width", "height"} - set(data)
        if missing:
            raise ValueError(f"camera intrinsics are missing keys {sorted(missing)}")
        return cls(*(strict_number(data[k], k) for k in ("fx", "fy", "cx", "cy")),
                   *(strict_integer(data[k], k) for k in ("width", "height")))


def strict_number(value, name: str) -> float:
    """A number read from a file as float; strings and booleans are refused, not converted.

    Raises:
        ValueError: ``"<name> must be a number, got <value>"``.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    return float(value)


def strict_integer(value, name: str) -> int:
    """A whole number read from a file (``8`` or ``8.0``) as int; fractions, infinities,
    strings and booleans are refused.

    Raises:
        ValueError: ``"<name> must be an integer, got <value>"``.
    """
    number = strict_number(value, name)
    if not math.isfinite(number) or number != round(number):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(number)


#: The ZJU-L5 test camera (RealSense D435i colour at 480x640), from the DELTAR paper.
ZJU_L5_INTRINSICS = CameraIntrinsics(611.2, 609.6, 323.4, 244.9, 640, 480)


def check_image(image: np.ndarray, name: str = "image",
                size: tuple[int, int] | None = None) -> np.ndarray:
    """Check a colour image: (H, W, 3) uint8 RGB, at least 2x2 pixels, and (H, W) =
    ``size`` pixels when given. The one image check of the package: readers, writers,
    baselines and the estimator call it at their boundary.

    Args:
        image: the image (anything ``np.asarray`` takes).
        name: what the messages call it (an argument, a file).
        size: the (height, width) in pixels it must have, or None for any size.

    Returns:
        The image as a C-contiguous (H, W, 3) uint8 array (no copy when it is one).

    Raises:
        ValueError: naming ``name``, when the shape, dtype or size is wrong.
    """
    array = np.asarray(image)
    if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"{name} must be an (H, W, 3) uint8 RGB image, got shape "
                         f"{array.shape} and dtype {array.dtype}")
    if array.shape[0] < 2 or array.shape[1] < 2:
        raise ValueError(f"{name} is too small: {array.shape[0]}x{array.shape[1]} pixels")
    if size is not None and array.shape[:2] != tuple(size):
        raise ValueError(f"{name} is {array.shape[0]}x{array.shape[1]} pixels, expected "
                         f"{size[0]}x{size[1]}")
    return np.ascontiguousarray(array)


def _check_depth(depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be an (H, W) array, got shape {depth.shape}")
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(f"depth_m is {depth.shape[0]}x{depth.shape[1]} pixels but the "
                         f"intrinsics are for {intrinsics.height}x{intrinsics.width} images")
    if np.isnan(depth).any():
        raise ValueError("depth_m contains NaN; mark invalid pixels with 0")
    return depth


def pixel_rays(intrinsics: CameraIntrinsics, height: int | None = None,
               width: int | None = None) -> np.ndarray:
    """Rays ``K^-1 (u, v, 1) = ((u - cx) / fx, (v - cy) / fy, 1)`` of a pixel grid.

    Args:
        intrinsics: camera intrinsics (pixels).
        height, width: grid size in pixels; the intrinsics' image size by default.

    Returns:
        (H, W, 3) float64 rays with z component 1, so ``depth * ray`` is the point.
    """
    height = intrinsics.height if height is None else int(height)
    width = intrinsics.width if width is None else int(width)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                     np.ones_like(u)], axis=-1)


def backproject_pixels(depth_m: np.ndarray, intrinsics: CameraIntrinsics, *,
                       mask: np.ndarray | None = None, stride: int = 1
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project the valid pixels of a depth map, with the pixels they come from.

    Args:
        depth_m: (H, W) z-depth in metres; pixels that are 0, negative or infinite are
            invalid (skipped); NaN is refused.
        intrinsics: intrinsics of the (H, W) image.
        mask: optional (H, W) bool, only pixels where True are used.
        stride: keep every ``stride``-th row and column (from row and column 0).

    Returns:
        points (N, 3) float64 in metres (camera frame: x right, y down, z forward),
        and the (N,) row and column indices of their pixels, in row-major order.

    Raises:
        ValueError: depth_m is not (H, W) of the intrinsics' size, contains NaN, the
            mask has another shape or the stride is not a positive integer.
    """
    depth = _check_depth(depth_m, intrinsics)
    if int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride!r}")
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != depth.shape:
            raise ValueError(f"mask must have shape {depth.shape}, got {mask.shape}")
        valid &= mask
    rows, cols = np.nonzero(valid[::stride, ::stride])
    rows, cols = rows * int(stride), cols * int(stride)
    z = depth[rows, cols]
    points = np.stack([(cols - intrinsics.cx) / intrinsics.fx * z,
                       (rows - intrinsics.cy) / intrinsics.fy * z, z], axis=1)
    return points, rows, cols


def backproject(depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                mask: np.ndarray | None = None, *, stride: int = 1) -> np.ndarray:
    """3D points (camera frame, metres) of the valid pixels of a depth map.

    The points of :func:`backproject_pixels` (same arguments and errors).

    Returns:
        (N, 3) float64 points (x, y, z) in metres, row-major pixel order.
    """
    return backproject_pixels(depth_m, intrinsics, mask=mask, stride=stride)[0]


def distortion_fold_error(intrinsics: CameraIntrinsics,
                          distortion: tuple[float, ...]) -> str | None:
    """Why a lens distortion cannot undistort the whole image, or None when it can.

    OpenCV's radial model maps a pinhole radius ``r`` (normalised coordinates) to a lens
    radius ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)``. The model holds for the image only if that
    map rises all the way to the image corners in both: if it turns back at a pinhole
    radius inside them, the undistorted image folds (pincushion-like fits); if the
    largest lens radius it reaches lies inside them, the image's outer pixels have no
    pinhole position and undistorting leaves them out (barrel-like fits).

    Args:
        intrinsics: fx, fy, cx, cy (pixels) and the image size.
        distortion: OpenCV's (k1, k2, p1, p2[, k3, ...]); the radial terms are checked.

    Returns:
        ``"lens distortion (k1 .., k2 ..) turns back at N % of the way ..."``, or None.
    """
    k1, k2 = [*distortion, 0.0, 0.0][:2]
    k3 = distortion[4] if len(distortion) > 4 else 0.0
    # d/dr of r (1 + k1 u + k2 u^2 + k3 u^3), u = r^2: 1 + 3 k1 u + 5 k2 u^2 + 7 k3 u^3.
    roots = np.roots([7 * k3, 5 * k2, 3 * k1, 1.0])
    turns = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
    if not turns:
        return None
    u = min(turns)
    # The turning point's pinhole radius and the lens radius it reaches.
    reach = min(math.sqrt(u), math.sqrt(u) * (1 + k1 * u + k2 * u * u + k3 * u ** 3))
    xs = (np.array([-0.5, intrinsics.width - 0.5]) - intrinsics.cx) / intrinsics.fx
    ys = (np.array([-0.5, intrinsics.height - 0.5]) - intrinsics.cy) / intrinsics.fy
    corner = float(np.hypot(np.abs(xs).max(), np.abs(ys).max()))
    if reach >= corner:
        return None
    terms = f"k1 {k1:.4g}, k2 {k2:.4g}" + (f", k3 {k3:.4g}" if k3 else "")
    return (f"lens distortion ({terms}) turns back at {100 * reach / corner:.0f} % of the "
            "way from the principal point to the image corners, so it cannot map the "
            "whole image: undistorting folds or leaves out the outer part")


def undistorted_coverage(intrinsics: CameraIntrinsics, distortion: tuple[float, ...],
                         samples: int = 48) -> float:
    """The fraction of the undistorted image (same intrinsics) whose pixels have a source
    pixel in the camera's image; the rest is black after undistortion. 1.0 without
    distortion; a real lens keeps nearly all of it.

    Args:
        intrinsics: fx, fy, cx, cy (pixels) and the image size.
        distortion: OpenCV coefficients (k1, k2, p1, p2[, k3, ...]).
        samples: grid points a side where it is evaluated.
    """
    if not any(distortion):
        return 1.0
    import cv2

    width, height = intrinsics.width, intrinsics.height
    cells = (np.arange(samples) + 0.5) / samples  # each grid point stands for its cell
    u, v = np.meshgrid(cells * width - 0.5, cells * height - 0.5)
    rays = np.stack([(u.ravel() - intrinsics.cx) / intrinsics.fx,
                     (v.ravel() - intrinsics.cy) / intrinsics.fy, np.ones(u.size)], axis=1)
    matrix = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy],
                       [0, 0, 1]], dtype=np.float64)
    with np.errstate(all="ignore"):
        source, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), matrix,
                                      np.asarray(distortion, dtype=np.float64))
    x, y = source.reshape(-1, 2).T
    inside = np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x <= width - 0.5) & \
        (y >= -0.5) & (y <= height - 0.5)
    return float(inside.mean())
