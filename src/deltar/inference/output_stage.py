"""The output stage on the network's output grid: the zones' readings reproduced, the
confidence blend, then calibrated sigma.

:meth:`~deltar.inference.estimator.DepthEstimator.predict` applies both on the grid the
network returns its maps on (half its input size) and resizes only what it returns to
the image's size: the maps carry no finer detail, and the per-pixel work shrinks with
the pixel count (a 480 x 640 image has 15 times the cells of its 128 x 160 grid).
Blending before or after the resize differs only where the blend weight changes within
a grid cell (what that does on the ten-scene protocol: benchmarks/RESULTS.md).
"""

from __future__ import annotations

import numpy as np

from deltar.inference.blend import ConfidenceBlend, blend_with_fill, grid_box
from deltar.inference.preprocess import resize_to_image
from deltar.inference.uncertainty import UncertaintyCalibration
from deltar.inference.zone_consistency import zone_consistent_depth


def apply_output_stage(depth_m: np.ndarray, spread_m: np.ndarray, fill_m: np.ndarray | None,
                       zone_rects: np.ndarray, blend: ConfidenceBlend | None,
                       uncertainty: UncertaintyCalibration | None, image_only: bool,
                       zone_readings: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                       zone_consistency: float = 0.0,
                       no_target: tuple[np.ndarray, float] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Correct, blend and calibrate one frame's maps on the network's output grid.

    Args:
        depth_m: (h, w) the network's depth, metres.
        spread_m: (h, w) its spread, metres.
        fill_m: the blend's fill (:func:`~deltar.inference.blend.blend_fill`), metres,
            on this grid or any other (resized to it), or None: no blend (none asked for,
            or no valid zone on the image to fill from).
        zone_rects: (Z, 4) zone rectangles in pixels of this grid.
        blend: the blend's coefficients (used when ``fill_m`` is given).
        uncertainty: the sigma calibration, or None for the raw spread.
        image_only: the frame has no valid zone: the metric scale is unknown, so the
            returned sigma is at least the depth.
        zone_readings: (mean_m, sigma_m, valid) of the frame's zones as screened, each
            (Z,) or (n, n), for the zone-consistency step; None skips it.
        zone_consistency: its strength in [0, 1]
            (:func:`~deltar.inference.zone_consistency.zone_consistent_depth`); the
            corrected depth is then the network's depth everything after reads.
        no_target: ((Z,) bool zones that reported no target, the sensor's range in
            metres): the calibrated sigma of their cells is at least the depth's distance
            beyond the range (:func:`no_target_sigma_floor`); None leaves it, and so does
            a missing ``uncertainty`` (the raw spread is what the output-stage fits read).

    Returns:
        (depth, sigma, network depth) (h, w) float32 metres; the network's depth is None
        when nothing was blended (then it is the returned depth).
    """
    if image_only:
        spread_m = np.maximum(spread_m, depth_m)
    if zone_readings is not None and zone_consistency > 0 and not image_only:
        depth_m = zone_consistent_depth(depth_m, zone_rects, *zone_readings, zone_consistency)
    network_depth = None
    depth = depth_m
    if fill_m is not None and blend is not None:
        network_depth = depth_m
        if fill_m.shape != depth_m.shape:  # a fill for another grid
            fill_m = resize_to_image(fill_m[None, None], depth_m.shape)[0, 0]
        depth = blend_with_fill(depth_m, spread_m, fill_m, zone_rects, blend)
    sigma = spread_m
    if uncertainty is not None:
        moved = np.zeros_like(depth) if network_depth is None else np.abs(network_depth - depth)
        sigma = uncertainty.sigma(spread_m, depth, moved, grid_box(zone_rects, depth.shape))
        if image_only:
            sigma = np.maximum(sigma, depth)
        if no_target is not None:  # the raw spread stays raw: the fits read it
            sigma = no_target_sigma_floor(sigma, depth, zone_rects, *no_target)
    return depth, sigma, network_depth


def no_target_sigma_floor(sigma_m: np.ndarray, depth_m: np.ndarray, zone_rects: np.ndarray,
                          no_target: np.ndarray, range_m: float) -> np.ndarray:
    """Sigma at least ``depth - range_m`` on the cells of zones that reported no target.

    Such a zone says only that its surface lies beyond the sensor's range: the depth
    placed there (the weights' no-target depth, or what the network made of it) is a
    prior, not a measurement, and a sigma fitted on measured pixels understates how far
    off it can be (on the ten-scene protocol's held-out rooms, 28-51 % of those pixels
    lay within one fitted sigma, 55-70 % within two: benchmarks/RESULTS.md). The floor
    spans the range limit from the depth, the one thing the reading says; cells the
    network put nearer than the range keep their sigma.

    Args:
        sigma_m: (h, w) sigma, metres.
        depth_m: (h, w) depth, metres.
        zone_rects: (Z, 4) zone rectangles in pixels of this grid.
        no_target: (Z,) bool, the zones that reported no target.
        range_m: the sensor's range, metres.

    Returns:
        (h, w) float32 sigma, metres (``sigma_m`` itself when no zone reported no target).
    """
    flags = np.asarray(no_target, dtype=bool).reshape(-1)
    if not flags.any():
        return sigma_m
    sigma = np.array(sigma_m, dtype=np.float32)
    for rect in np.asarray(zone_rects)[flags]:
        box = grid_box(rect[None], sigma.shape)
        np.maximum(sigma[box], depth_m[box] - np.float32(range_m), out=sigma[box])
    return sigma
