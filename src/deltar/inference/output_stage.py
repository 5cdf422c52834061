"""The output stage on the network's output grid: confidence blend, then calibrated sigma.

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


def apply_output_stage(depth_m: np.ndarray, spread_m: np.ndarray, fill_m: np.ndarray | None,
                       zone_rects: np.ndarray, blend: ConfidenceBlend | None,
                       uncertainty: UncertaintyCalibration | None, image_only: bool
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Blend and calibrate one frame's maps on the network's output grid.

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

    Returns:
        (depth, sigma, network depth) (h, w) float32 metres; the network's depth is None
        when nothing was blended (then it is the returned depth).
    """
    if image_only:
        spread_m = np.maximum(spread_m, depth_m)
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
