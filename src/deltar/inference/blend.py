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
    relative = uncertainty_m / np.maximum(depth_m, 1e-6)
    beta = np.where(inside, blend.beta_inside, blend.beta_outside)
    return np.exp(-beta * relative).astype(np.float32)


def blend_depth(depth_m: np.ndarray, uncertainty_m: np.ndarray, image_rgb: np.ndarray,
                zone_mean_m: np.ndarray, zone_valid: np.ndarray, zone_rects: np.ndarray,
                blend: ConfidenceBlend, zone_far: np.ndarray | None = None,
                far_depth_m: float | None = None) -> np.ndarray:
    """The network's depth blended with the colorization fill of the zone readings.

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
    from deltar.inference.colorization import colorize_zones  # scipy and cv2: on use

    if not isinstance(blend, ConfidenceBlend):
        raise ValueError(f"blend must be a ConfidenceBlend, got {blend!r}")
    depth_m = np.asarray(depth_m)
    shape = depth_m.shape
    if depth_m.ndim != 2:
        raise ValueError(f"depth_m must be an (H, W) map, got shape {shape}")
    if np.shape(uncertainty_m) != shape:
        raise ValueError(f"uncertainty_m must have depth_m's shape {shape}, got "
                         f"{np.shape(uncertainty_m)}")
    if np.shape(image_rgb)[:2] != shape:
        raise ValueError(f"image_rgb must be (H, W, 3) with depth_m's (H, W) = {shape}, got "
                         f"{np.shape(image_rgb)}")
    means = np.asarray(zone_mean_m, dtype=np.float64).reshape(-1)
    if np.shape(zone_valid) != means.shape:
        raise ValueError(f"zone_valid must have zone_mean_m's shape {means.shape}, got "
                         f"{np.shape(zone_valid)}")
    valid = np.asarray(zone_valid, dtype=bool) & (means > 0)
    if not valid.any():
        return depth_m
    if zone_far is not None:
        if far_depth_m is None or not (math.isfinite(far_depth_m) and far_depth_m > 0):
            raise ValueError(f"far_depth_m must be a finite depth > 0 (metres) with zone_far, "
                             f"got {far_depth_m!r}")
        if np.shape(zone_far) != means.shape:
            raise ValueError(f"zone_far must have zone_mean_m's shape {means.shape}, got "
                             f"{np.shape(zone_far)}")
        means, valid = no_target_as_readings(means, valid, zone_far, far_depth_m)
    fill = colorize_zones(image_rgb, means, valid, zone_rects)
    if fill is None:  # no valid zone overlaps the image
        return depth_m
    weight = blend_weight(depth_m, uncertainty_m, zone_grid_mask(zone_rects, depth_m.shape),
                          blend)
    return (weight * depth_m + (1.0 - weight) * fill).astype(np.float32)
