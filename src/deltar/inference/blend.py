"""Confidence blend: the network's depth where it is sure, a global fill where it is not.

The plane-select network gives each pixel the depth of the zone planes its image
descriptors pick. Where the pick is clear its depth is better per pixel than any
classical method's; where it is unsure (mixed zones at depth edges, and most of what the
camera sees beyond the sensor's field of view) a wrong pick costs a large error. The
colorization fill of the zone readings (:func:`deltar.inference.colorization.colorize_zones`,
the classical ``colorization`` baseline) errs differently: it propagates the readings
smoothly along the image, so it hedges. The blend mixes the two in log depth, per pixel:

    log depth = w log network + (1 - w) log fill
    w = sigmoid(bias + spread_slope * log(uncertainty / network))

with one ``(bias, spread_slope)`` for pixels inside the zone grid's bounding box and one
for the pixels beyond it (where the network extrapolates). Both parts are metric from
the zones and ``w`` depends on a ratio only, so scaling every reading by ``k`` scales
the blended depth by ``k``. (A third term on the disagreement ``|log(network / fill)|``
fitted lower errors on the training scenes and higher ones on the scenes left out, so
the weight reads the network's own uncertainty alone.)

The coefficients are fitted on frames with ground truth
(:func:`deltar.inference.blend_fit.fit_confidence_blend`,
run by ``deltar fit-uncertainty`` on a model's training scenes) and travel in the
network's config (``confidence_blend``); a plane-select checkpoint without them uses
:data:`DEFAULT_BLEND`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from deltar.inference.regions import RegionPair, check_coefficients
from deltar.sensor.zone_frame import no_target_as_readings


@dataclass(frozen=True)
class RegionBlend:
    """Logistic weight of the network's log depth in one region (module docstring).

    Attributes:
        bias: the weight's logit where the network's relative uncertainty is 1.
        spread_slope: logit change per unit of ``log(uncertainty / depth)`` (negative:
            the less sure the network, the more the fill counts).
    """

    bias: float
    spread_slope: float

    def __post_init__(self) -> None:
        check_coefficients(self, "confidence blend")

    def logit(self, log_relative_spread: np.ndarray) -> np.ndarray:
        """The weight's logit (float32, same shape) from ``log(uncertainty / depth)``."""
        return np.float32(self.bias) + np.float32(self.spread_slope) * log_relative_spread


@dataclass(frozen=True)
class ConfidenceBlend(RegionPair, region_type=RegionBlend, what="confidence blend"):
    """Blend coefficients inside and beyond the zone grid (module docstring); the fields,
    their checks and the JSON form (``to_dict`` / ``from_dict``) are :class:`RegionPair`'s."""

    inside: RegionBlend
    outside: RegionBlend


#: The blend of a plane-select checkpoint that carries none: fitted with
#: :func:`~deltar.inference.blend_fit.fit_confidence_blend` on the ten shared RGB-D
#: scenes (clean and degraded zones, simulated with up to four targets per zone) with the
#: bundled model (docs/training.md).
DEFAULT_BLEND = ConfidenceBlend(inside=RegionBlend(-6.184, -4.392),
                                outside=RegionBlend(-4.913, -3.810))


def resolve_blend(blend: ConfidenceBlend | str | None, contract: Mapping
                  ) -> ConfidenceBlend | None:
    """The blend an estimator uses (its ``blend`` argument) given the weights' contract.

    ``"auto"``: plane-select networks blend with the coefficients the weights carry
    (``contract["confidence_blend"]``) or :data:`DEFAULT_BLEND`, other networks do not;
    a ``ConfidenceBlend`` as it is; None never.

    Raises:
        ValueError: anything else.
    """
    if blend == "auto":
        if contract.get("head") != "plane_select":
            return None
        stored = contract.get("confidence_blend")
        return DEFAULT_BLEND if stored is None else ConfidenceBlend.from_dict(stored)
    if blend is not None and not isinstance(blend, ConfidenceBlend):
        raise ValueError(f"blend must be 'auto', a ConfidenceBlend or None, got {blend!r}")
    return blend


def zone_grid_mask(zone_rects: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels inside the bounding box of all zone rectangles.

    Args:
        zone_rects: (Z, 4) (y0, x0, y1, x1) in image pixels (may run past the image).
        image_size: (H, W) pixels.
    """
    mask = np.zeros(tuple(image_size), dtype=bool)
    mask[grid_box(zone_rects, image_size)] = True
    return mask


def grid_box(zone_rects: np.ndarray, image_size: tuple[int, int]) -> tuple[slice, slice]:
    """(rows, cols) slices of :func:`zone_grid_mask`'s True pixels (arguments as there:
    (Z, 4) rectangles and the (H, W) size, pixels)."""
    height, width = image_size
    rects = np.asarray(zone_rects, dtype=np.float64)
    y0 = int(np.clip(np.floor(rects[:, 0].min()), 0, height))
    x0 = int(np.clip(np.floor(rects[:, 1].min()), 0, width))
    y1 = int(np.clip(np.ceil(rects[:, 2].max()), 0, height))
    x1 = int(np.clip(np.ceil(rects[:, 3].max()), 0, width))
    return slice(y0, y1), slice(x0, x1)


def blend_weight(depth_m: np.ndarray, uncertainty_m: np.ndarray, inside: np.ndarray,
                 blend: ConfidenceBlend) -> np.ndarray:
    """(H, W) float32 weight in [0, 1] of the network's log depth (module docstring).

    Args:
        depth_m: (H, W) network depth, metres (> 0).
        uncertainty_m: (H, W) its standard deviation, metres (>= 0).
        inside: (H, W) bool, True inside the zone grid (:func:`zone_grid_mask`).
        blend: the coefficients.
    """
    return _weight(log_relative_spread(depth_m, uncertainty_m), inside, blend)


def log_relative_spread(depth_m: np.ndarray, uncertainty_m: np.ndarray,
                        log_depth: np.ndarray | None = None) -> np.ndarray:
    """``log(uncertainty / depth)``, float32, any one shape (both floored at 1e-6 m).

    ``log_depth``: ``log(max(depth_m, 1e-6))`` (float32) when the caller has it already.
    """
    if log_depth is None:
        log_depth = _log_floored(depth_m)
    log_spread = _log_floored(uncertainty_m)
    log_spread -= log_depth
    return log_spread


def _log_floored(values: np.ndarray) -> np.ndarray:
    """float32 ``log(max(values, 1e-6))`` in a new array of ``values``' shape.

    OpenCV's vectorised log and maximum: the same accuracy as NumPy's (about 2e-7
    relative) at a quarter of their time on CPUs without AVX-512, where NumPy's float32
    log is not vectorised.
    """
    import cv2

    values = np.ascontiguousarray(values, dtype=np.float32)
    if values.size < 8:  # OpenCV reads an array of up to four values as a scalar
        return np.log(np.maximum(values, np.float32(1e-6)))
    floored = cv2.max(values.reshape(-1, 1), 1e-6)  # OpenCV reads (N, 1) as a matrix
    cv2.log(floored, floored)
    return floored.reshape(values.shape)


def _exp_in_place(values: np.ndarray) -> np.ndarray:
    """``exp`` of a contiguous float32 array, in place (OpenCV's, as :func:`_log_floored`)."""
    import cv2

    if values.size < 8 or not values.flags.c_contiguous:  # as _log_floored; a view
        return np.exp(values, out=values)
    flat = values.reshape(-1, 1)
    cv2.exp(flat, flat)
    return values


def _weight(log_spread: np.ndarray, inside: np.ndarray, blend: ConfidenceBlend) -> np.ndarray:
    logit = np.where(inside, blend.inside.logit(log_spread), blend.outside.logit(log_spread))
    return _logistic(logit.astype(np.float32, copy=False))


def _weight_in_box(log_spread: np.ndarray, box: tuple[slice, slice],
                   blend: ConfidenceBlend) -> np.ndarray:
    """:func:`_weight` for an inside region that is a rectangle (``box``): the same values
    in fewer passes over the map."""
    logit = blend.outside.logit(log_spread)
    logit[box] = blend.inside.logit(log_spread[box])
    return _logistic(logit)


def _logistic(logit: np.ndarray) -> np.ndarray:
    """float32 ``1 / (1 + exp(-logit))`` of a clipped logit (no overflow in exp), computed
    in the float32 array ``logit``, which it returns."""
    np.clip(logit, -60.0, 60.0, out=logit)
    np.negative(logit, out=logit)
    _exp_in_place(logit)
    logit += np.float32(1.0)
    return np.divide(np.float32(1.0), logit, out=logit)


#: Accuracy of the blend's fill solve (``colorize_zones``' ``tolerance``): one refinement
#: step of the single-precision LU, which leaves about 1e-7 of the readings' scale
#: (float32's own rounding), where the classical baseline refines to float64's 1e-10.
BLEND_FILL_TOLERANCE = 1e-3
#: Cells of the blend's fill solve (``colorize_zones``' ``solve_cells``) and the side of
#: each zone's seed square in them.
BLEND_FILL_CELLS = 2400
BLEND_FILL_SEED_SIDE = 3


def blend_fill(image_rgb: np.ndarray, zone_mean_m: np.ndarray, zone_valid: np.ndarray,
               zone_rects: np.ndarray, zone_far: np.ndarray | None = None,
               far_depth_m: float | None = None, out_size: tuple[int, int] | None = None
               ) -> np.ndarray | None:
    """The fill that :func:`blend_depth` blends with: the zones' colorization (metres).

    It needs only the image and the zones, so a stream can compute it while the network
    runs (:func:`deltar.inference.fill_schedule.start_blend_fill`). Arguments as
    :func:`blend_depth`'s; ``out_size`` (h, w) pixels of the returned map covering the
    whole image (the image's size by default; the estimator asks for its network's
    output grid and blends there). Solved on :data:`BLEND_FILL_CELLS` cells to
    :data:`BLEND_FILL_TOLERANCE`, guided by the image halved (:func:`halved_guide`).

    Returns:
        (H, W) (or ``out_size``) float32 fill, metres, or None when no valid zone (on
        the image) is there to fill from.

    Raises:
        ValueError: as :func:`blend_depth` for the zone and image arguments.
    """
    from deltar.inference.colorization import (  # scipy and cv2: on use
        colorization_guide,
        colorize_zones,
    )

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
    from deltar.camera import check_image

    image_rgb = check_image(image_rgb, "image_rgb")
    size = image_rgb.shape[:2]
    guide = colorization_guide(halved_guide(image_rgb, BLEND_FILL_CELLS), BLEND_FILL_CELLS,
                               source_size=size)
    if guide.image_size != size:  # made from the halved image
        from deltar.inference.preprocess import scale_rects

        zone_rects = scale_rects(zone_rects, size, guide.image_size)
        out_size = size if out_size is None else out_size
    return colorize_zones(guide, means, valid, zone_rects, solve_cells=BLEND_FILL_CELLS,
                          seed_side=BLEND_FILL_SEED_SIDE, tolerance=BLEND_FILL_TOLERANCE,
                          out_size=out_size)


def halved_guide(image_rgb: np.ndarray, solve_cells: int) -> np.ndarray:
    """The fill's guide image halved (2 x 2 area means,
    :func:`~deltar.inference.preprocess.halved_while`) while it keeps at least twice the
    resolution of a ``solve_cells`` grid along each side and both sides stay even.

    The fill's area resize to its grid (e.g. 42 x 57 for 480 x 640) then reads 4 to 16
    times fewer pixels, and averages the same areas (to the halvings' uint8 roundings).

    Args:
        image_rgb: (H, W, 3) uint8 RGB image.
        solve_cells: cells of the fill's solve grid.

    Returns:
        (H / 2^n, W / 2^n, 3) uint8 (``image_rgb`` itself when n = 0).
    """
    from deltar.inference.preprocess import halved_while

    height, width = np.shape(image_rgb)[:2]
    scale = math.sqrt(solve_cells / max(1, height * width))
    return halved_while(image_rgb, (2 * height * scale, 2 * width * scale))


def blend_with_fill(depth_m: np.ndarray, uncertainty_m: np.ndarray, fill_m: np.ndarray,
                    zone_rects: np.ndarray, blend: ConfidenceBlend) -> np.ndarray:
    """``depth_m ** w * fill_m ** (1 - w)`` with :func:`blend_weight`'s ``w``.

    Args:
        depth_m: (H, W) network depth, metres.
        uncertainty_m: (H, W) its standard deviation, metres.
        fill_m: (H, W) fill (:func:`blend_fill`), metres.
        zone_rects: (Z, 4) zone rectangles in image pixels.
        blend: the coefficients.

    Returns:
        (H, W) float32 blended depth, metres.
    """
    depth_m = np.asarray(depth_m, dtype=np.float32)
    if np.shape(fill_m) != depth_m.shape:
        raise ValueError(f"fill_m must have depth_m's shape {depth_m.shape}, got "
                         f"{np.shape(fill_m)}")
    # blend_weight then mix_log_depth, with the log of the depth taken once and the
    # zone grid's box as slices (no mask).
    log_depth = _log_floored(depth_m)
    weight = _weight_in_box(log_relative_spread(depth_m, uncertainty_m, log_depth),
                            grid_box(zone_rects, depth_m.shape), blend)
    return mix_log_depth(depth_m, np.asarray(fill_m, dtype=np.float32), weight, log_depth)


def mix_log_depth(depth_m: np.ndarray, fill_m: np.ndarray, weight: np.ndarray,
                  log_depth: np.ndarray | None = None) -> np.ndarray:
    """``exp(w log depth_m + (1 - w) log fill_m)``: float32, metres, any one shape.

    Exactly ``depth_m`` where ``w`` is 1 and ``fill_m`` where it is 0. ``log_depth``:
    ``log(max(depth_m, 1e-6))`` (float32) when the caller has it already.
    """
    log_fill = _log_floored(fill_m)
    if log_depth is None:
        log_depth = _log_floored(depth_m)
    mixed = log_depth - log_fill
    mixed *= weight
    mixed += log_fill
    out = _exp_in_place(np.ascontiguousarray(mixed, dtype=np.float32))
    # exp(log x) is x only to a rounding: keep the two ends exact.
    np.copyto(out, depth_m, where=weight >= 1.0)
    np.copyto(out, fill_m, where=weight <= 0.0)
    return out


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
        blend: the coefficients.
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
