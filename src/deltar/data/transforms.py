"""Image-level training augmentation for RGB-D frames (geometry + photometry).

What DELTAR's release does when training on NYU: random rotation within +-2.5 degrees,
random crop, horizontal flip and, half of the time, gamma / brightness / per-channel colour
jitter. Everything here is driven by an explicit ``numpy.random.Generator`` so that a
dataset can seed it per item and epoch.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from deltar.camera import CameraIntrinsics


@dataclass
class AugmentedFrame:
    """Result of :meth:`ImageAugmentation.apply`.

    Attributes:
        image: (H, W, 3) float32 RGB in [0, 1].
        depth_m: (H, W) float32 metres, 0.0 where invalid (including rotated-in borders).
        intrinsics: intrinsics of the output image.
        crop_top, crop_left: where the output starts in the (rotated) input, pixels.
        flipped: whether the output is mirrored left-right.
    """

    image: np.ndarray
    depth_m: np.ndarray
    intrinsics: CameraIntrinsics
    crop_top: int = 0
    crop_left: int = 0
    flipped: bool = False


@dataclass(frozen=True)
class ImageAugmentation:
    """Random rotation, crop, horizontal flip and colour jitter (release defaults).

    Attributes:
        crop_size: (height, width) of the random crop in pixels; None keeps the full image.
        max_rotation_deg: rotation drawn uniformly from +- this many degrees (about the
            image centre; the ToF sensor is rigidly attached, so zones rotate with it).
        flip_prob: probability of a horizontal flip.
        photometric_prob: probability of applying gamma, brightness and colour jitter.
        gamma_range, brightness_range, color_range: uniform ranges of the jitter factors.
        max_zoom: random zoom by a factor drawn uniformly from [1, max_zoom]: a window of
            1 / zoom of each side, at a random place, is resized back to the full size,
            which multiplies the focal lengths by the zoom (another camera's
            intrinsics). 1 disables it.
    """

    crop_size: tuple[int, int] | None = None
    max_rotation_deg: float = 2.5
    flip_prob: float = 0.5
    photometric_prob: float = 0.5
    gamma_range: tuple[float, float] = (0.9, 1.1)
    brightness_range: tuple[float, float] = (0.75, 1.25)
    color_range: tuple[float, float] = (0.9, 1.1)
    max_zoom: float = 1.0

    def __post_init__(self) -> None:
        if not 1.0 <= self.max_zoom <= 4.0:
            raise ValueError(f"ImageAugmentation.max_zoom must be in [1, 4], got {self.max_zoom}")
        if self.crop_size is not None and (len(self.crop_size) != 2 or min(self.crop_size) < 1):
            raise ValueError(f"ImageAugmentation.crop_size must be (height, width) > 0, got "
                             f"{self.crop_size}")
        for name in ("flip_prob", "photometric_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"ImageAugmentation.{name} must be in [0, 1]")
        if not 0.0 <= self.max_rotation_deg < 90.0:
            raise ValueError("ImageAugmentation.max_rotation_deg must be in [0, 90)")

    def apply(self, image: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
              rng: np.random.Generator) -> AugmentedFrame:
        """Augment one frame.

        Args:
            image: (H, W, 3) uint8 RGB.
            depth_m: (H, W) float32 metres, 0 where invalid.
            intrinsics: intrinsics of ``image``.
            rng: drives every random choice (same state -> same output).

        Returns:
            The augmented frame (see :class:`AugmentedFrame`).

        Raises:
            ValueError: ``crop_size`` is larger than the image.
        """
        height, width = depth_m.shape
        img = image.astype(np.float32) / 255.0
        depth = depth_m.astype(np.float32)
        if self.max_rotation_deg > 0:
            angle = float(rng.uniform(-self.max_rotation_deg, self.max_rotation_deg))
            rot = cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), angle, 1.0)
            img = cv2.warpAffine(img, rot, (width, height), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            # Nearest neighbour: interpolating depth across an edge invents surfaces.
            depth = cv2.warpAffine(depth, rot, (width, height), flags=cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        top = left = 0
        intr = intrinsics
        if self.max_zoom > 1.0:
            zoom = float(rng.uniform(1.0, self.max_zoom))
            win_h, win_w = max(1, round(height / zoom)), max(1, round(width / zoom))
            y0 = int(rng.integers(0, height - win_h + 1))
            x0 = int(rng.integers(0, width - win_w + 1))
            img = cv2.resize(img[y0:y0 + win_h, x0:x0 + win_w], (width, height),
                             interpolation=cv2.INTER_LINEAR)
            depth = cv2.resize(depth[y0:y0 + win_h, x0:x0 + win_w], (width, height),
                               interpolation=cv2.INTER_NEAREST)
            intr = intr.cropped(y0, x0, win_h, win_w).scaled(height, width)
        if self.crop_size is not None:
            crop_h, crop_w = (int(v) for v in self.crop_size)
            if crop_h > height or crop_w > width:
                raise ValueError(f"crop_size {self.crop_size} is larger than the image "
                                 f"{height}x{width}")
            top = int(rng.integers(0, height - crop_h + 1))
            left = int(rng.integers(0, width - crop_w + 1))
            img = img[top:top + crop_h, left:left + crop_w]
            depth = depth[top:top + crop_h, left:left + crop_w]
            intr = intr.cropped(top, left, crop_h, crop_w)
        flipped = bool(rng.random() < self.flip_prob)
        if flipped:
            img, depth = img[:, ::-1], depth[:, ::-1]
            intr = flip_intrinsics(intr)
        if rng.random() < self.photometric_prob:
            gamma = rng.uniform(*self.gamma_range)
            brightness = rng.uniform(*self.brightness_range)
            colors = rng.uniform(*self.color_range, size=3).astype(np.float32)
            img = np.clip(img**gamma * brightness * colors, 0.0, 1.0)
        return AugmentedFrame(np.ascontiguousarray(img, dtype=np.float32),
                              np.ascontiguousarray(depth, dtype=np.float32), intr, top, left,
                              flipped)


def flip_intrinsics(intrinsics: CameraIntrinsics) -> CameraIntrinsics:
    """Intrinsics of the left-right mirrored image (pixel centres at integers)."""
    return CameraIntrinsics(intrinsics.fx, intrinsics.fy, intrinsics.width - 1 - intrinsics.cx,
                            intrinsics.cy, intrinsics.width, intrinsics.height)
