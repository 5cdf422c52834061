"""Confidence blend: the network's depth where it is sure, a global fill where it is not.

The plane-select network gives each pixel the depth of the zone planes its image
descriptors pick. Where the pick is clear its depth is better per pixel than any
classical method's; where it is unsure (mixed zones at depth edges, and most of what the
camera sees beyond the sensor's field of view) a wrong pick costs a large error. The
colorization fill of the zone readings (:func:`deltar.inference.colorization.colorize_zones`,
the classical ``colorization`` baseline)
errs differently: it propagates the readings smoothly along the image, so it hedges. The
blend takes, per pixel,

    depth = w * network + (1 - w) * fill,   w = exp(-beta * uncertainty / network)

with ``beta_inside`` for pixels inside the zone grid's bounding box and ``beta_outside``
beyond it (where the network extrapolates). Both parts are metric from the zones and
``w`` is a ratio, so scaling every reading by ``k`` scales the blended depth by ``k``.

The betas were chosen leave-one-scene-out (docs/training.md): on each fold the pair that
did best on the three other scenes; three of the four folds chose (8, 128).
"""

from __future__ import annotations

import math
import numbers
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from deltar.sensor.zone_frame import no_target_as_readings


@dataclass(frozen=True)
class ConfidenceBlend:
    """Blend weights of :func:`blend_depth` (see the module docstring).

    Attributes:
        beta_inside: weight decay per unit of relative uncertainty inside the zone grid.
        beta_outside: the same beyond the zone grid's bounding box.
    """

    beta_inside: float = 8.0
    beta_outside: float = 128.0

    def __post_init__(self) -> None:
        for name in ("beta_inside", "beta_outside"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, numbers.Real)
                                               and math.isfinite(value) and value >= 0):
                raise ValueError(f"ConfidenceBlend.{name} must be a finite number >= 0, got "
                                 f"{value!r}")


def zone_grid_mask(zone_rects: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels inside the bounding box of all zone rectangles.

    Args:
        zone_rects: (Z, 4) (y0, x0, y1, x1) in image pixels (may run past the image).
        image_size: (H, W) pixels.
    """
    height, width = image_size
    rects = np.asarray(zone_rects, dtype=np.float64)
    y0 = int(np.clip(np.floor(rects[:, 0].min()), 0, height))
    x0 = int(np.clip(np.floor(rects[:, 1].min()), 0, width))
    y1 = int(np.clip(np.ceil(rects[:, 2].max()), 0, height))
    x1 = int(np.clip(np.ceil(rects[:, 3].max()), 0, width))
    mask = np.zeros((height, width), dtype=bool)
    mask[y0:y1, x0:x1] = True
    return mask


def blend_weight(depth_m: np.ndarray, uncertainty_m: np.ndarray, inside: np.ndarray,
                 blend: ConfidenceBlend) -> np.ndarray:
    """(H, W) float32 weight in (0, 1] of the network's depth (module docstring).

    Args:
        depth_m: (H, W) network depth, metres (> 0).
        uncertainty_m: (H, W) its standard deviation, metres (>= 0).
        inside: (H, W) bool, True inside the zone grid (:func:`zone_grid_mask`).
        blend: the betas.
    """
    # float32 throughout: a 480 x 640 frame's weight in about a millisecond.
    depth_m = np.asarray(depth_m, dtype=np.float32)
    relative = np.asarray(uncertainty_m, dtype=np.float32) / np.maximum(depth_m,
                                                                       np.float32(1e-6))
    relative *= np.where(inside, np.float32(-blend.beta_inside),
                         np.float32(-blend.beta_outside))
    return np.exp(relative, out=relative)


def blend_fill(image_rgb: np.ndarray, zone_mean_m: np.ndarray, zone_valid: np.ndarray,
               zone_rects: np.ndarray, zone_far: np.ndarray | None = None,
               far_depth_m: float | None = None) -> np.ndarray | None:
    """The fill that :func:`blend_depth` blends with: the zones' colorization (metres).

    It needs only the image and the zones, so a stream can compute it while the network
    runs (:func:`start_blend_fill`). Arguments as :func:`blend_depth`'s.

    Returns:
        (H, W) float32 fill, metres, or None when no valid zone (on the image) is there
        to fill from.

    Raises:
        ValueError: as :func:`blend_depth` for the zone and image arguments.
    """
    from deltar.inference.colorization import colorize_zones  # scipy and cv2: on use

    means = np.asarray(zone_mean_m, dtype=np.float64).reshape(-1)
    if np.shape(zone_valid) != means.shape:
        raise ValueError(f"zone_valid must have zone_mean_m's shape {means.shape}, got "
                         f"{np.shape(zone_valid)}")
    valid = np.asarray(zone_valid, dtype=bool) & (means > 0)
    if not valid.any():
        return None
    if zone_far is not None:
        if far_depth_m is None or not (math.isfinite(far_depth_m) and far_depth_m > 0):
            raise ValueError(f"far_depth_m must be a finite depth > 0 (metres) with zone_far, "
                             f"got {far_depth_m!r}")
        if np.shape(zone_far) != means.shape:
            raise ValueError(f"zone_far must have zone_mean_m's shape {means.shape}, got "
                             f"{np.shape(zone_far)}")
        means, valid = no_target_as_readings(means, valid, zone_far, far_depth_m)
    return colorize_zones(image_rgb, means, valid, zone_rects)


_FILL_WORKER: ThreadPoolExecutor | None = None
_FILL_WORKER_LOCK = threading.Lock()


def start_blend_fill(image_rgb: np.ndarray, zone_mean_m: np.ndarray, zone_valid: np.ndarray,
                     zone_rects: np.ndarray, zone_far: np.ndarray | None = None,
                     far_depth_m: float | None = None) -> Future:
    """:func:`blend_fill` on a worker thread; its ``Future`` gives the fill (or raises).

    The fill spends most of its time in LAPACK and OpenCV, which release the GIL, so it
    runs beside the network (onnxruntime and PyTorch release the GIL too). One worker
    thread, shared by all estimators, started on first use.
    """
    global _FILL_WORKER
    with _FILL_WORKER_LOCK:
        if _FILL_WORKER is None:
            _FILL_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-fill")
    return _FILL_WORKER.submit(blend_fill, image_rgb, zone_mean_m, zone_valid, zone_rects,
                               zone_far, far_depth_m)


def blend_with_fill(depth_m: np.ndarray, uncertainty_m: np.ndarray, fill_m: np.ndarray,
                    zone_rects: np.ndarray, blend: ConfidenceBlend) -> np.ndarray:
    """``w * depth_m + (1 - w) * fill_m`` with :func:`blend_weight`'s ``w``.

    Args:
        depth_m: (H, W) network depth, metres.
        uncertainty_m: (H, W) its standard deviation, metres.
        fill_m: (H, W) fill (:func:`blend_fill`), metres.
        zone_rects: (Z, 4) zone rectangles in image pixels.
        blend: the betas.

    Returns:
        (H, W) float32 blended depth, metres.
    """
    depth_m = np.asarray(depth_m, dtype=np.float32)
    if np.shape(fill_m) != depth_m.shape:
        raise ValueError(f"fill_m must have depth_m's shape {depth_m.shape}, got "
                         f"{np.shape(fill_m)}")
    weight = blend_weight(depth_m, uncertainty_m, zone_grid_mask(zone_rects, depth_m.shape),
                          blend)
    fill_m = np.asarray(fill_m, dtype=np.float32)
    # In place, float32: exactly the network where w = 1 and the fill where w = 0.
    blended = weight * depth_m
    np.subtract(np.float32(1.0), weight, out=weight)
    weight *= fill_m
    blended += weight
    return blended


def blend_depth(depth_m: np.ndarray, uncertainty_m: np.ndarray, image_rgb: np.ndarray,
                zone_mean_m: np.ndarray, zone_valid: np.ndarray, zone_rects: np.ndarray,
                blend: ConfidenceBlend, zone_far: np.ndarray | None = None,
                far_depth_m: float | None = None) -> np.ndarray:
    """The network's depth blended with the colorization fill of the zone readings.

    :func:`blend_fill` then :func:`blend_with_fill`.

    Args:
        depth_m: (H, W) network depth at the image's resolution, metres.
        uncertainty_m: (H, W) its standard deviation, metres.
        image_rgb: (H, W, 3) uint8 RGB image (the fill's guide).
        zone_mean_m: (Z,) zone readings, metres.
        zone_valid: (Z,) bool.
        zone_rects: (Z, 4) zone rectangles in image pixels.
        blend: the betas.
        zone_far: (Z,) bool, optional: zones that reported no target; where not valid
            they join the fill as readings at ``far_depth_m`` (as the network reads them).
        far_depth_m: depth of a no-target zone, metres (required with ``zone_far``).

    Returns:
        (H, W) float32 blended depth, metres. Without a valid zone overlapping the image
        the fill has nothing to propagate: ``depth_m`` itself is returned (the same
        object, so a caller can tell).

    Raises:
        ValueError: mismatched shapes (naming the argument), ``blend`` not a
            :class:`ConfidenceBlend`, ``zone_far`` without a finite ``far_depth_m`` > 0,
            or bad zone arrays (:func:`~deltar.inference.colorization.colorize_zones`).
    """
    check_blend_inputs(depth_m, uncertainty_m, image_rgb, blend)
    fill = blend_fill(image_rgb, zone_mean_m, zone_valid, zone_rects, zone_far, far_depth_m)
    if fill is None:  # no valid zone (on the image)
        return depth_m
    return blend_with_fill(depth_m, uncertainty_m, fill, zone_rects, blend)


def check_blend_inputs(depth_m: np.ndarray, uncertainty_m: np.ndarray, image_rgb: np.ndarray,
                       blend: ConfidenceBlend) -> None:
    """ValueError naming the argument unless depth, uncertainty and image are one (H, W)."""
    if not isinstance(blend, ConfidenceBlend):
        raise ValueError(f"blend must be a ConfidenceBlend, got {blend!r}")
    shape = np.shape(depth_m)
    if len(shape) != 2:
        raise ValueError(f"depth_m must be an (H, W) map, got shape {shape}")
    if np.shape(uncertainty_m) != shape:
        raise ValueError(f"uncertainty_m must have depth_m's shape {shape}, got "
                         f"{np.shape(uncertainty_m)}")
    if np.shape(image_rgb)[:2] != shape:
        raise ValueError(f"image_rgb must be (H, W, 3) with depth_m's (H, W) = {shape}, got "
                         f"{np.shape(image_rgb)}")
