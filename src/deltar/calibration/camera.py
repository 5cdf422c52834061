"""Pinhole camera intrinsics."""

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
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"CameraIntrinsics.{name} must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"CameraIntrinsics focal lengths must be > 0, got fx={self.fx}, "
                             f"fy={self.fy}")
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
        missing = {"fx", "fy", "cx", "cy", "width", "height"} - set(data)
        if missing:
            raise ValueError(f"camera intrinsics are missing keys {sorted(missing)}")
        return cls(float(data["fx"]), float(data["fy"]), float(data["cx"]), float(data["cy"]),
                   int(data["width"]), int(data["height"]))


#: The ZJU-L5 test camera (RealSense D435i colour at 480x640), from the DELTAR paper.
ZJU_L5_INTRINSICS = CameraIntrinsics(611.2, 609.6, 323.4, 244.9, 640, 480)
