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
                       zone_consistency: float = 0.0
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
    return depth, sigma, network_depth
