"""Classical baselines: dense depth from the zone means and the RGB image, no training.

Three families, all taking the same inputs (the image and one sensor frame):

- super-resolution of the zone-mean map: ``nearest`` (each pixel takes the value of the
  zone whose rectangle holds its centre), ``bilinear`` and ``bicubic`` (interpolation
  between zone centres), plus ``median`` (one constant, the median zone mean);
- RGB-guided upsampling of the nearest map: ``guided_filter`` (He et al., colour guide,
  built from box filters) and ``joint_bilateral`` (joint bilateral filter);
- depth completion: ``colorization`` (zone means placed at the zone centres and filled
  with Levin et al.'s colorization, as ``fill_depth_colorization`` of the NYU toolbox,
  solved at reduced resolution and upsampled).

Invalid zones are ignored. Pixels outside the sensor's field of view take the value of
the nearest valid zone (super-resolution) or a smooth, image-guided fill (completion);
no output pixel is ever 0 or NaN. With no valid zone at all every baseline returns the
constant ``fallback_depth_m`` (default :data:`DEFAULT_FALLBACK_DEPTH_M`, 2 m, about the
middle of the L5's 4 m range) and warns.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.ndimage

from deltar.camera import check_image
from deltar.inference.colorization import (
    COLORIZATION_SEED_SIDE,
    COLORIZATION_SOLVE_CELLS,
    colorize_zones,
)
from deltar.sensor.geometry import zone_rects_to_pixel_bounds

#: Depth returned everywhere when a frame has no valid zone (metres).
DEFAULT_FALLBACK_DEPTH_M = 2.0


@dataclass(frozen=True)
class BaselineInputs:
    """The checked inputs of the classical baselines (:func:`check_baseline_inputs`).

    Attributes:
        image: (H, W, 3) uint8 RGB image.
        mean_m: (Z,) float64 zone means in metres (0 for invalid zones).
        valid: (Z,) bool zone validity.
        rects: (Z, 4) float64 zone rectangles (y0, x0, y1, x1) in pixels.
        grid: zones per side (Z = grid * grid).
    """

    image: np.ndarray
    mean_m: np.ndarray
    valid: np.ndarray
    rects: np.ndarray
    grid: int

    @property
    def height(self) -> int:
        """Image rows, pixels."""
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        """Image columns, pixels."""
        return int(self.image.shape[1])

    @property
    def pitch_px(self) -> float:
        """Median zone size in pixels (mean of height and width)."""
        sizes = np.concatenate([self.rects[:, 2] - self.rects[:, 0],
                                self.rects[:, 3] - self.rects[:, 1]])
        return float(np.median(sizes))


def check_baseline_inputs(
    image_rgb: np.ndarray,
    zone_mean_m: np.ndarray,
    zone_valid: np.ndarray,
    zone_rects: np.ndarray,
) -> BaselineInputs:
    """Validate and convert the inputs shared by all baselines.

    Args:
        image_rgb: (H, W, 3) uint8 RGB image.
        zone_mean_m: (Z,) zone means in metres; Z must be a square (16, 64, ...).
        zone_valid: (Z,) bool validity; invalid zones may hold any value.
        zone_rects: (Z, 4) rectangles (y0, x0, y1, x1) in pixels, row-major zone order.

    Returns:
        The checked inputs as a :class:`BaselineInputs`.

    Raises:
        ValueError: a shape, dtype or value is wrong (the message names the argument).
    """
    image = check_image(image_rgb, "image_rgb")
    mean = np.asarray(zone_mean_m, dtype=np.float64).reshape(-1)
    valid = np.asarray(zone_valid).reshape(-1)
    if valid.dtype != np.bool_:
        if not np.all(np.isin(valid, (0, 1))):
            raise ValueError("zone_valid must be boolean (or 0/1)")
        valid = valid.astype(bool)
    rects = np.asarray(zone_rects, dtype=np.float64)
    zones = mean.size
    grid = math.isqrt(zones)
    if grid < 2 or grid * grid != zones:
        raise ValueError(f"zone_mean_m must hold a square number (>= 4) of zones, got {zones}")
    if valid.shape != (zones,):
        raise ValueError(f"zone_valid must have shape ({zones},), got {valid.shape}")
    if rects.shape != (zones, 4):
        raise ValueError(f"zone_rects must have shape ({zones}, 4), got {rects.shape}")
    if not np.all(np.isfinite(rects)):
        raise ValueError("zone_rects contains NaN or infinite values")
    if np.any(rects[:, 2] <= rects[:, 0]) or np.any(rects[:, 3] <= rects[:, 1]):
        raise ValueError("zone_rects must satisfy y1 > y0 and x1 > x0 for every zone")
    valid_means = mean[valid]
    if not np.all(np.isfinite(valid_means)) or np.any(valid_means <= 0):
        raise ValueError("zone_mean_m must be finite and > 0 for every valid zone")
    mean = np.where(valid, mean, 0.0)
    return BaselineInputs(image, mean, valid, rects, grid)


def _fallback(inputs: BaselineInputs, fallback_depth_m: float) -> np.ndarray:
    warnings.warn(f"no valid zone: returning the constant fallback depth "
                  f"{fallback_depth_m} m", RuntimeWarning, stacklevel=3)
    return np.full((inputs.height, inputs.width), fallback_depth_m, dtype=np.float32)


def _fractional_index(coords: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Map pixel coordinates to fractional grid indices, piecewise linear between centres.

    Beyond the first and last centre the map continues linearly with the end pitch, so
    interpolation with border replication extrapolates the edge zones' values.
    """
    if np.any(np.diff(centres) <= 0):
        raise ValueError("zone_rects centres must increase along rows and columns "
                         "(row-major zones as they appear in the image)")
    index = np.interp(coords, centres, np.arange(centres.size, dtype=np.float64))
    first_pitch = centres[1] - centres[0]
    last_pitch = centres[-1] - centres[-2]
    before, after = coords < centres[0], coords > centres[-1]
    index[before] = (coords[before] - centres[0]) / first_pitch
    index[after] = centres.size - 1 + (coords[after] - centres[-1]) / last_pitch
    return index


def _filled_grid(inputs: BaselineInputs) -> np.ndarray:
    """(grid, grid) zone means with each invalid zone set to its nearest valid zone."""
    values = inputs.mean_m.reshape(inputs.grid, inputs.grid)
    invalid = ~inputs.valid.reshape(inputs.grid, inputs.grid)
    if not invalid.any():
        return values.copy()
    nearest = scipy.ndimage.distance_transform_edt(invalid, return_distances=False,
                                                    return_indices=True)
    return values[nearest[0], nearest[1]]


def _grid_upsample(inputs: BaselineInputs, interpolation: int) -> np.ndarray:
    """Interpolate the filled zone grid at every pixel (OpenCV remap, edges replicated)."""
    grid = inputs.grid
    centres_y = 0.5 * (inputs.rects[:, 0] + inputs.rects[:, 2]).reshape(grid, grid)
    centres_x = 0.5 * (inputs.rects[:, 1] + inputs.rects[:, 3]).reshape(grid, grid)
    # One centre per grid row / column: robust to slightly sheared calibrated layouts.
    row_centres = np.median(centres_y, axis=1)
    col_centres = np.median(centres_x, axis=0)
    map_y = _fractional_index(np.arange(inputs.height, dtype=np.float64), row_centres)
    map_x = _fractional_index(np.arange(inputs.width, dtype=np.float64), col_centres)
    map_x, map_y = np.meshgrid(map_x.astype(np.float32), map_y.astype(np.float32))
    source = _filled_grid(inputs).astype(np.float32)
    return cv2.remap(source, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)


def _nearest_zone_map(inputs: BaselineInputs) -> np.ndarray:
    """Each pixel takes the value of the valid zone whose rectangle holds its centre.

    Pixels no valid zone covers take the value of the nearest covered pixel. Where zone
    rectangles overlap, the later zone (row-major order) wins.
    """
    depth = np.zeros((inputs.height, inputs.width), dtype=np.float64)
    covered = np.zeros((inputs.height, inputs.width), dtype=bool)
    bounds = zone_rects_to_pixel_bounds(inputs.rects, inputs.height, inputs.width)
    for (y0, x0, y1, x1), value in zip(bounds[inputs.valid], inputs.mean_m[inputs.valid],
                                       strict=True):
        depth[y0:y1, x0:x1] = value
        covered[y0:y1, x0:x1] = True
    if not covered.any():
        # Every valid zone lies outside the image: extrapolate from the zone grid instead.
        return _grid_upsample(inputs, cv2.INTER_NEAREST)
    if not covered.all():
        nearest = scipy.ndimage.distance_transform_edt(~covered, return_distances=False,
                                                        return_indices=True)
        depth = depth[nearest[0], nearest[1]]
    return depth


def _valid_range(inputs: BaselineInputs) -> tuple[float, float]:
    values = inputs.mean_m[inputs.valid]
    return float(values.min()), float(values.max())


def upsample_zone_means(inputs: BaselineInputs, method: str = "bilinear") -> np.ndarray:
    """Super-resolve the zone-mean map to the image size.

    Args:
        inputs: checked inputs with at least one valid zone.
        method: ``"nearest"`` (zone rectangles painted, uncovered pixels from the nearest
            covered pixel), ``"bilinear"`` or ``"bicubic"`` (interpolation between zone
            centres, edge zones extended outwards; bicubic is clipped to the range of the
            valid zone means so it cannot overshoot to negative depth).

    Returns:
        (H, W) float32 depth in metres.
    """
    if not inputs.valid.any():
        raise ValueError("upsample_zone_means needs at least one valid zone")
    if method == "nearest":
        depth = _nearest_zone_map(inputs)
    elif method == "bilinear":
        depth = _grid_upsample(inputs, cv2.INTER_LINEAR)
    elif method == "bicubic":
        depth = np.clip(_grid_upsample(inputs, cv2.INTER_CUBIC), *_valid_range(inputs))
    else:
        raise ValueError(f"method must be 'nearest', 'bilinear' or 'bicubic', got {method!r}")
    return depth.astype(np.float32)


def _box(array: np.ndarray, radius: int) -> np.ndarray:
    """Mean over a (2 radius + 1)^2 window, reflected at the borders (per channel)."""
    size = 2 * radius + 1
    return cv2.boxFilter(array, -1, (size, size), normalize=True,
                         borderType=cv2.BORDER_REFLECT)


def guided_filter(source: np.ndarray, guide: np.ndarray, radius: int,
                  eps: float = 1e-3) -> np.ndarray:
    """He et al.'s guided filter with a colour guide, from box filters.

    The output is locally an affine function of the guide's colour, fitted to
    ``source`` in each window, so edges of the guide carry over to the output.

    Args:
        source: (H, W) float image to filter (e.g. depth in metres).
        guide: (H, W, 3) float guide, values in [0, 1].
        radius: window radius in pixels (window = 2 radius + 1).
        eps: regularisation of the local colour covariance (guide units squared); larger
            values smooth more.

    Returns:
        (H, W) float64 filtered image.
    """
    source = np.asarray(source, dtype=np.float64)
    guide = np.asarray(guide, dtype=np.float64)
    if guide.shape[:2] != source.shape or guide.ndim != 3 or guide.shape[2] != 3:
        raise ValueError(f"guide must be (H, W, 3) matching source {source.shape}, "
                         f"got {guide.shape}")
    if radius < 1 or eps <= 0:
        raise ValueError(f"need radius >= 1 and eps > 0, got radius={radius}, eps={eps}")
    mean_i = _box(guide, radius)  # (H, W, 3)
    mean_p = _box(source, radius)
    cov_ip = _box(guide * source[..., None], radius) - mean_i * mean_p[..., None]
    # Per-pixel 3x3 colour covariance from the 6 distinct products.
    pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    products = np.stack([guide[..., i] * guide[..., j] for i, j in pairs], axis=-1)
    mean_products = _box(products, radius)
    sigma = np.empty((*source.shape, 3, 3))
    for k, (i, j) in enumerate(pairs):
        covariance = mean_products[..., k] - mean_i[..., i] * mean_i[..., j]
        sigma[..., i, j] = sigma[..., j, i] = covariance
    sigma += eps * np.eye(3)
    a = np.linalg.solve(sigma, cov_ip[..., None])[..., 0]  # (H, W, 3)
    b = mean_p - np.sum(a * mean_i, axis=-1)
    return np.sum(_box(a, radius) * guide, axis=-1) + _box(b, radius)


def joint_bilateral_filter(source: np.ndarray, guide: np.ndarray, radius: int,
                           sigma_space: float, sigma_color: float, step: int = 1) -> np.ndarray:
    """Joint (cross) bilateral filter: average ``source`` with weights from space and guide.

    ``out(p) = sum_q w(p, q) source(q) / sum_q w(p, q)`` with
    ``w = exp(-|p - q|^2 / (2 sigma_space^2)) * exp(-|guide(p) - guide(q)|^2 / (2 sigma_color^2))``
    over the window offsets ``-radius..radius`` in steps of ``step`` pixels (a sparse
    window keeps large radii cheap). Vectorised over pixels; one pass per offset.

    Args:
        source: (H, W) float image to filter (e.g. depth in metres).
        guide: (H, W, C) float guide (e.g. RGB in [0, 1]).
        radius: window radius in pixels.
        sigma_space: spatial Gaussian sigma in pixels.
        sigma_color: range Gaussian sigma in guide units.
        step: spacing of the window offsets in pixels.

    Returns:
        (H, W) float32 filtered image.
    """
    source = np.asarray(source, dtype=np.float32)
    guide = np.asarray(guide, dtype=np.float32)
    if guide.ndim == 2:
        guide = guide[..., None]
    if guide.shape[:2] != source.shape:
        raise ValueError(f"guide must be (H, W, C) matching source {source.shape}, "
                         f"got {guide.shape}")
    if radius < 1 or step < 1 or sigma_space <= 0 or sigma_color <= 0:
        raise ValueError("need radius >= 1, step >= 1, sigma_space > 0 and sigma_color > 0")
    height, width = source.shape
    pad = ((radius, radius), (radius, radius))
    source_pad = np.pad(source, pad, mode="edge")
    # Channels first and in-place arithmetic: contiguous slices, no per-tap allocations.
    guide = np.ascontiguousarray(np.moveaxis(guide, -1, 0))
    guide_pad = np.stack([np.pad(channel, pad, mode="edge") for channel in guide])
    numerator = np.zeros_like(source)
    denominator = np.zeros_like(source)
    weight = np.empty_like(source)
    scratch = np.empty_like(source)
    inv_color = np.float32(-0.5 / sigma_color**2)
    offsets = range(-(radius // step) * step, radius + 1, step)
    for dy in offsets:
        for dx in offsets:
            rows = slice(radius + dy, radius + dy + height)
            cols = slice(radius + dx, radius + dx + width)
            weight.fill(0.0)
            for channel in range(guide.shape[0]):
                np.subtract(guide_pad[channel, rows, cols], guide[channel], out=scratch)
                np.multiply(scratch, scratch, out=scratch)
                weight += scratch
            weight *= inv_color
            weight += np.float32(-0.5 * (dy * dy + dx * dx) / sigma_space**2)
            np.exp(weight, out=weight)
            denominator += weight
            weight *= source_pad[rows, cols]
            numerator += weight
    # The centre offset (0, 0) is always in the window, so the denominator is >= 1.
    return numerator / denominator


def complete_colorization(inputs: BaselineInputs, solve_cells: int = COLORIZATION_SOLVE_CELLS,
                          seed_side: int = COLORIZATION_SEED_SIDE) -> np.ndarray:
    """The ``colorization`` baseline: :func:`deltar.inference.colorization.colorize_zones`
    of the checked inputs (``solve_cells`` cells, seeds of ``seed_side`` cells), or the
    ``nearest`` map when no valid zone overlaps the image.

    Returns:
        (H, W) float32 depth in metres.
    """
    depth = colorize_zones(inputs.image, inputs.mean_m, inputs.valid, inputs.rects,
                           solve_cells=solve_cells, seed_side=seed_side)
    return upsample_zone_means(inputs, "nearest") if depth is None else depth


def _guide(inputs: BaselineInputs) -> np.ndarray:
    return inputs.image.astype(np.float32) / 255.0


def _nearest(inputs: BaselineInputs) -> np.ndarray:
    return upsample_zone_means(inputs, "nearest")


def _bilinear(inputs: BaselineInputs) -> np.ndarray:
    return upsample_zone_means(inputs, "bilinear")


def _bicubic(inputs: BaselineInputs) -> np.ndarray:
    return upsample_zone_means(inputs, "bicubic")


def _median(inputs: BaselineInputs) -> np.ndarray:
    value = float(np.median(inputs.mean_m[inputs.valid]))
    return np.full((inputs.height, inputs.width), value, dtype=np.float32)


def _guided(inputs: BaselineInputs) -> np.ndarray:
    # Window about half a zone: edges move to image edges within half a zone of the
    # zone boundaries, while zone interiors keep their measured mean.
    radius = max(1, round(0.5 * inputs.pitch_px))
    depth = guided_filter(_nearest(inputs), _guide(inputs), radius, eps=1e-3)
    return np.clip(depth, *_valid_range(inputs)).astype(np.float32)


def _joint_bilateral(inputs: BaselineInputs) -> np.ndarray:
    radius = max(1, round(0.5 * inputs.pitch_px))
    step = max(1, radius // 5)  # about 11 x 11 taps whatever the zone size
    depth = joint_bilateral_filter(_nearest(inputs), _guide(inputs), radius,
                                   sigma_space=0.5 * radius, sigma_color=0.1, step=step)
    return depth.astype(np.float32)


def _colorization(inputs: BaselineInputs) -> np.ndarray:
    return complete_colorization(inputs)


_BASELINE_FUNCTIONS: dict[str, Callable[[BaselineInputs], np.ndarray]] = {
    "median": _median,
    "nearest": _nearest,
    "bilinear": _bilinear,
    "bicubic": _bicubic,
    "guided_filter": _guided,
    "joint_bilateral": _joint_bilateral,
    "colorization": _colorization,
}

#: Names accepted by :func:`run_baseline`.
BASELINES: tuple[str, ...] = tuple(_BASELINE_FUNCTIONS)


def run_baseline(
    name: str,
    image_rgb: np.ndarray,
    zone_mean_m: np.ndarray,
    zone_valid: np.ndarray,
    zone_rects: np.ndarray,
    *,
    fallback_depth_m: float = DEFAULT_FALLBACK_DEPTH_M,
) -> np.ndarray:
    """Dense depth from one image and one sensor frame with a classical baseline.

    Args:
        name: one of :data:`BASELINES`.
        image_rgb: (H, W, 3) uint8 RGB image.
        zone_mean_m: (Z,) zone means in metres (Z = 16, 64, ... a square).
        zone_valid: (Z,) bool; invalid zones are ignored.
        zone_rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in image pixels; may be
            non-integer and run past the image.
        fallback_depth_m: constant depth returned (with a warning) when no zone is valid.

    Returns:
        (H, W) float32 depth in metres, finite and > 0 everywhere.

    Raises:
        ValueError: unknown ``name`` (the message lists the valid ones) or bad inputs.
    """
    if name not in _BASELINE_FUNCTIONS:
        raise ValueError(f"unknown baseline {name!r}; valid names: {', '.join(BASELINES)}")
    if not (math.isfinite(fallback_depth_m) and fallback_depth_m > 0):
        raise ValueError(f"fallback_depth_m must be finite and > 0, got {fallback_depth_m}")
    inputs = check_baseline_inputs(image_rgb, zone_mean_m, zone_valid, zone_rects)
    if not inputs.valid.any():
        return _fallback(inputs, fallback_depth_m)
    return _BASELINE_FUNCTIONS[name](inputs).astype(np.float32)
