"""What the network sees: the one size rule, image normalisation, and the mappings of
zone rectangles into the network input and of its output back to the image.

Every path that runs a network on camera images uses this module: ``DepthEstimator``
(PyTorch and onnxruntime), ``deltar export`` (the fixed input size of an ONNX file) and
``deltar evaluate`` (through the estimator). The rule, for an H x W image and a model
designed (trained) at ``design_size`` = (h_d, w_d) pixels:

1. Scale the image, keeping its aspect ratio, to the design size's pixel budget:
   ``s = sqrt(h_d * w_d / (H * W))`` (larger images shrink, smaller ones grow), so the
   network sees the scene at the scale it learned, at the cost it was designed for,
   whatever the camera's resolution and aspect.
2. Round each side to the nearest multiple of 32 (the encoder's coarsest stride), at
   least 32. This is the only change of aspect: at most 16 pixels per side.

Without a design size (a model that declares none) step 1 is skipped. A fixed size
(``DepthEstimator(input_size=...)``, ``deltar predict --size``, or the size an ONNX
file was exported at) replaces the rule; an ONNX export at several sizes takes the
rule's size when it was exported, else the exported size nearest in aspect. The image
is resized to the network size (area averaging when shrinking, bilinear when
enlarging), the zone rectangles are mapped with the same per-axis scales
(:func:`scale_rects`), and the network's depth and uncertainty (half the network size)
are resized bilinearly back to H x W (:func:`resize_to_image`). Pixel centres sit at
integer coordinates throughout.

The module works on numpy arrays (OpenCV resizes); it does not import torch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from deltar.contract import IMAGENET_MEAN, IMAGENET_STD, SIZE_DIVISOR


def network_input_size(height: int, width: int,
                       design_size: Sequence[int] | None = None,
                       divisor: int = SIZE_DIVISOR) -> tuple[int, int]:
    """The network input size for an image: the rule of this module's docstring.

    Args:
        height, width: image size in pixels (positive).
        design_size: (H, W) in pixels the model was designed and trained for
            (``model.network_config.inputs.design_size``, stored in every checkpoint); None skips
            the scaling to its pixel budget.
        divisor: required multiple (32 for DeltarNet).

    Returns:
        (height, width) in pixels, each a positive multiple of ``divisor``.

    Raises:
        ValueError: a non-positive image size, design size or divisor (the message
            names the argument).

    Example: with the bundled model's design size 256x320, a 480x640 image runs at
    256x320, 480x480 at 288x288, 720x1280 at 224x384 and 16x4000 at 32x4512.
    """
    if int(divisor) < 1:
        raise ValueError(f"divisor must be a positive number of pixels, got {divisor!r}")
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    scale = 1.0
    if design_size is not None:
        design = tuple(design_size)
        if len(design) != 2 or min(design) < 1:
            raise ValueError(f"design_size must be a positive (height, width) in pixels, got "
                             f"{design_size!r}")
        scale = math.sqrt(design[0] * design[1] / (height * width))
    return (max(divisor, round(height * scale / divisor) * divisor),
            max(divisor, round(width * scale / divisor) * divisor))


def check_input_size(input_size: Sequence[int], name: str = "input_size",
                     divisor: int = SIZE_DIVISOR) -> tuple[int, int]:
    """A fixed network input size as (H, W) ints, checked to be positive multiples.

    Raises:
        ValueError: naming ``name`` when a side is not a positive multiple of ``divisor``.
    """
    try:
        height, width = (int(s) for s in input_size)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be (height, width) in pixels, got {input_size!r}") from err
    if height < divisor or width < divisor or height % divisor or width % divisor:
        raise ValueError(f"{name} must be positive multiples of {divisor}, got {input_size}")
    return height, width


def scale_rects(rects: np.ndarray, from_size: tuple[int, int],
                to_size: tuple[int, int]) -> np.ndarray:
    """Map (y0, x0, y1, x1) rectangles from one image size to a resized image.

    Pixel centres sit at integer coordinates, so the image spans ``-0.5 .. size - 0.5``
    and a coordinate ``c`` maps to ``(c + 0.5) * scale - 0.5``, with one scale per axis
    (``to / from``), exactly as the image itself is resized.

    Args:
        rects: (..., 4) rectangles in pixels of an image of ``from_size`` (H, W).
        from_size: (H, W) of the source image, pixels.
        to_size: (H, W) of the resized image, pixels.

    Returns:
        (..., 4) float32 rectangles in pixels of the resized image.
    """
    rects = np.asarray(rects, dtype=np.float64)
    sy = to_size[0] / from_size[0]
    sx = to_size[1] / from_size[1]
    scale = np.array([sy, sx, sy, sx])
    return ((rects + 0.5) * scale - 0.5).astype(np.float32)


def normalise_images(images: Sequence[np.ndarray], size: tuple[int, int],
                     mean: Sequence[float] | None = None,
                     std: Sequence[float] | None = None) -> np.ndarray:
    """Resize RGB images to ``size`` and normalise them for the network.

    Args:
        images: B images, each (H, W, 3) uint8 RGB.
        size: (h, w) network input size in pixels.
        mean, std: per-channel normalisation for images in [0, 1], the network's input
            contract (``model.network_config.inputs.image_mean`` / ``image_std``); ImageNet's
            when None.

    Returns:
        (B, 3, h, w) float32, ``(rgb / 255 - mean) / std``.
    """
    import cv2

    if mean is None or std is None:
        mean, std = IMAGENET_MEAN, IMAGENET_STD
    height, width = size
    # One multiply-add per pixel: x * (1 / (255 std)) - mean / std.
    scale = (1.0 / (255.0 * np.asarray(std))).astype(np.float32)
    offset = (-np.asarray(mean) / np.asarray(std)).astype(np.float32)
    out = np.empty((len(images), 3, height, width), dtype=np.float32)
    for i, image in enumerate(images):
        # 480 x 640 to 256 x 320: halved to 240 x 320, then bilinearly to 256 rows (a
        # 2 x 2 box where an area resize's is 1.875 x 2 pixels).
        image = halved_while(image, (HALVING_FLOOR * height, HALVING_FLOOR * width))
        if image.shape[:2] != (height, width):
            shrink = image.shape[0] > height or image.shape[1] > width
            # Area averaging when shrinking (no aliasing), bilinear when enlarging; both
            # keep pixel centres at integer coordinates, as scale_rects assumes.
            image = cv2.resize(image, (width, height),
                               interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        # Per channel on contiguous planes, written straight into the output: several
        # times faster than converting the interleaved image and transposing it.
        for channel, plane in enumerate(cv2.split(np.ascontiguousarray(image))):
            np.multiply(plane, scale[channel], out=out[i, channel], dtype=np.float32)
            out[i, channel] += offset[channel]
    return out


#: :func:`normalise_images` halves an image (:func:`halved_while`) while both halved
#: sides keep at least this fraction of the network's input size.
HALVING_FLOOR = 0.9


def halved_while(image: np.ndarray, min_size: tuple[float, float]) -> np.ndarray:
    """An image halved (2 x 2 area means) while both its sides are even and both halved
    sides stay at least ``min_size``; the image itself when no halving applies.

    OpenCV's area resize has a fast path for exact halving only; its general path costs
    several times more per input pixel (1.8 ms for 480 x 640 to 256 x 320 on one core,
    against 0.2 ms for halving it), so a large image is halved first and resized the
    rest of the way from there.

    Args:
        image: (H, W, C) image.
        min_size: (h, w) pixels each halved side must keep.
    """
    import cv2

    height, width = image.shape[:2]
    while height % 2 == 0 and width % 2 == 0 and height // 2 >= min_size[0] \
            and width // 2 >= min_size[1]:
        height, width = height // 2, width // 2
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return image


def resize_to_image(maps: np.ndarray, image_size: tuple[int, int],
                    align_corners: bool = False) -> np.ndarray:
    """Resize network output maps back to the input image's resolution, bilinearly.

    Args:
        maps: (B, C, h, w) maps (depth, uncertainty: metres) in the network's output
            grid (half the network input size).
        image_size: (H, W) of the input image, pixels.
        align_corners: map the corner pixels' centres onto each other instead, as the
            released DELTAR code upsamples its output (torch's ``align_corners=True``).

    Returns:
        (B, C, H, W) float32 maps. OpenCV's bilinear resize, the same sampling as
        torch's ``interpolate(mode="bilinear", align_corners=False)`` (pixel centres map
        as in :func:`scale_rects`; equal within 5e-5 relative, the precision of either's
        float32 weights) and an order of magnitude faster at 480 x 640; with
        ``align_corners`` an OpenCV remap with the same sample positions as torch's.
    """
    import cv2

    height, width = (int(v) for v in image_size)
    maps = np.asarray(maps, dtype=np.float32)
    planes = maps.reshape(-1, *maps.shape[2:])
    out = np.empty((planes.shape[0], height, width), dtype=np.float32)
    if align_corners:  # separable, in exact float weights (OpenCV's are fixed-point)
        (y0, y1, wy), (x0, x1, wx) = (_aligned_taps(planes.shape[1], height),
                                      _aligned_taps(planes.shape[2], width))
        rows = planes[:, y0] + (planes[:, y1] - planes[:, y0]) * wy[:, None]
        out[:] = rows[:, :, x0] + (rows[:, :, x1] - rows[:, :, x0]) * wx
        return out.reshape(*maps.shape[:2], height, width)
    for plane, target in zip(planes, out, strict=True):
        cv2.resize(plane, (width, height), dst=target, interpolation=cv2.INTER_LINEAR)
    return out.reshape(*maps.shape[:2], height, width)


def _aligned_taps(size: int, out_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both source indices and the weight of the second for each of ``out_size`` samples
    spread from the first to the last of ``size`` pixel centres (``align_corners``)."""
    # In float32 steps, as torch computes them: the same sample positions to the bit.
    scale = np.float32((size - 1) / (out_size - 1)) if out_size > 1 else np.float32(0.0)
    position = np.arange(out_size, dtype=np.float32) * scale
    first = np.clip(np.floor(position).astype(np.int64), 0, max(size - 2, 0))
    second = np.minimum(first + 1, size - 1)
    return first, second, np.minimum(position - first, np.float32(1.0))
