"""Reading single RGB-D files: colour images, depth images, camera-matrix text files.

Depth images hold integers in ``1 / depth_scale`` metres (millimetres: scale 1000; TUM
benchmark: 5000); 0, 65535 and non-finite values are invalid and become 0.0. Every
path goes through the one reading boundary (:mod:`deltar.io.input_file`), so a missing,
unreadable or corrupt file is one error naming it. The folder readers built on these
are :mod:`deltar.data.rgbd`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from deltar.camera import CameraIntrinsics
from deltar.io.input_file import input_file, reading

#: Raw depth value that Kinect-style sensors write for "no reading" (besides 0).
_SATURATED_U16 = 65535


def read_color(path: str | Path) -> np.ndarray:
    """Decode a colour image file to (H, W, 3) uint8 RGB.

    8-bit grey and palette images are expanded to RGB, an alpha channel is dropped.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is corrupt or truncated, or holds one channel of more than
            8 bits (a 16-bit or float image is a depth map, not a colour image).
    """
    path = input_file(path, "colour image")
    with reading(path, "colour image"):
        try:
            with Image.open(path) as img:
                img.load()  # decode now: truncated files raise here, not later
                if img.mode in _DEPTH_LIKE_MODES:
                    raise ValueError(f"{path} is a single-channel "
                                     f"{_DEPTH_LIKE_MODES[img.mode]} image (a depth map?), "
                                     "not a colour image")
                return np.asarray(img.convert("RGB"), dtype=np.uint8).copy()
        except (OSError, UnidentifiedImageError, SyntaxError) as err:
            raise ValueError(f"cannot decode colour image {path}: {err}") from err


#: Pillow modes of single-channel images deeper than 8 bits, as depth maps are stored.
_DEPTH_LIKE_MODES = {"I;16": "16-bit", "I;16B": "16-bit", "I;16L": "16-bit",
                     "I;16N": "16-bit", "I": "32-bit integer", "F": "32-bit float"}


def check_depth_scale(depth_scale: float) -> float:
    """``depth_scale`` (raw depth units per metre) as a float.

    Raises:
        ValueError: not finite and > 0.
    """
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be finite and > 0, got {depth_scale}")
    return float(depth_scale)


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:
    """Decode a depth image to (H, W) float32 metres, 0.0 where invalid.

    Args:
        path: 16-bit PNG/TIFF/PGM (integers in ``1 / depth_scale`` metres) or ``.npy``
            (integers or floats, also in ``1 / depth_scale`` metres: 1 for float metres).
        depth_scale: raw units per metre (1000 for millimetres, 5000 for TUM).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is corrupt, not single-channel, ``depth_scale`` <= 0, or
            float depth that the scale puts within :data:`FLOAT_DEPTH_FLOOR_M` everywhere
            (metres read as millimetres).
    """
    path = Path(path)
    depth_scale = check_depth_scale(depth_scale)
    input_file(path, "depth image")
    with reading(path, "depth image"):
        try:
            if path.suffix.lower() == ".npy":
                raw = np.load(path, allow_pickle=False)
            else:
                with Image.open(path) as img:
                    img.load()
                    raw = np.asarray(img)
        except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as err:
            raise ValueError(f"cannot decode depth image {path}: {err}") from err
    if raw.ndim != 2:
        raise ValueError(f"depth image {path} must be single-channel, got shape {raw.shape}")
    if raw.dtype.kind not in "iuf" or raw.dtype.itemsize < 2:
        # 8 bits hold at most 255 units (0.255 m in millimetres): a grey picture or a
        # normalised visualisation, not a depth camera's depth.
        raise ValueError(f"depth image {path} holds {raw.dtype} values; depth images are "
                         "16-bit integers (1 / depth_scale metres) or float")
    invalid = ~np.isfinite(raw) if raw.dtype.kind == "f" else np.zeros(raw.shape, bool)
    if raw.dtype.kind in "iu":  # Pillow may decode 16-bit PNGs as uint16 or int32
        invalid |= raw == _SATURATED_U16
    depth = np.where(invalid, 0.0, raw.astype(np.float64) / depth_scale)
    depth[depth < 0] = 0.0
    if raw.dtype.kind == "f" and 0 < depth.max() < FLOAT_DEPTH_FLOOR_M:
        # Float depth is most often metres already: scaled again, a room would lie
        # within a few millimetres, nearer than any depth camera measures.
        raise ValueError(f"depth image {path}: float values up to {depth.max() * depth_scale:.4g}"
                         f" read as at most {depth.max() * 1000:.3g} mm with depth_scale "
                         f"{depth_scale:g}; if they are metres, set depth_scale to 1")
    return depth.astype(np.float32)


#: A float depth image whose every depth, after ``depth_scale``, lies nearer than this
#: (metres) is refused by :func:`read_depth`: metres divided by 1000.
FLOAT_DEPTH_FLOOR_M = 0.05


def color_image_size(path: str | Path) -> tuple[int, int]:
    """(height, width) in pixels of a colour image file, read from its header (the
    pixels are not decoded)."""
    input_file(path, "colour image")
    with reading(path, "colour image"):
        try:
            with Image.open(path) as img:
                return img.height, img.width
        except (OSError, UnidentifiedImageError) as err:
            raise ValueError(f"cannot read colour image {path}: {err}") from err


def default_intrinsics(height: int, width: int) -> CameraIntrinsics:
    """Kinect / PrimeSense default intrinsics (525 px focal length at 640x480), resized.

    Used when a folder does not record its intrinsics; TUM recommends these values for
    its data when no calibration is at hand.
    """
    base = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    return base if (height, width) == (480, 640) else base.scaled(height, width)


def read_intrinsics_matrix(path: str | Path, height: int, width: int) -> CameraIntrinsics:
    """Read a text 3x3 camera matrix (7-Scenes ``camera-intrinsics.txt`` style).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: it does not hold a valid 3x3 pinhole matrix.
    """
    path = Path(path)
    input_file(path, "intrinsics file")
    try:
        k = np.loadtxt(path, dtype=np.float64)
    except ValueError as err:
        raise ValueError(f"intrinsics file {path} is not a numeric 3x3 matrix: {err}") from err
    if k.shape != (3, 3):
        raise ValueError(f"intrinsics file {path} must hold a 3x3 matrix, got {k.shape}")
    return CameraIntrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)
