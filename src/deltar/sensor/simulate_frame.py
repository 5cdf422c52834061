"""One simulated sensor reading from one depth map, in numpy: :func:`simulate_zone_frame`.

The single-frame twin of the batched PyTorch simulator
(:func:`deltar.sensor.simulate.simulate_zones`, which the training data pipeline runs),
for the paths that run without PyTorch: ``deltar demo``, ``deltar simulate``,
``deltar record --simulate``, the simulated walls and rigs. Same steps and the same
float32 bin arithmetic (that of ``torch.histc``, as the official release), so the
histograms, validity and no-target flags are identical and the mean and sigma equal to
float rounding (tested against it):

1. histogram each zone's depth in ``bin_width_m`` bins over ``[0, max_range_m]``
   (depth beyond the range is left out; depth exactly at ``max_range_m`` falls into the
   last bin);
2. zero the first ``ignored_bins`` bins and subtract ``noise_floor_counts`` from every
   bin, clipping at zero;
3. keep the run of consecutive non-empty bins with the largest total (the first on ties);
4. report its count-weighted mean and (population) standard deviation of the bin centres;
   a zone with no counts left is invalid, and reports *no target* when more of its
   pixels lie beyond the range than within it.
"""

from __future__ import annotations

import math

import numpy as np

from deltar.sensor.geometry import zone_rects_to_pixel_bounds
from deltar.sensor.simulator_config import SimulatorConfig
from deltar.sensor.zone_frame import ZoneFrame

__all__ = ["depth_bins", "simulate_zone_frame", "strongest_run", "zone_depth_histograms"]


def depth_bins(depth_m: np.ndarray, config: SimulatorConfig) -> np.ndarray:
    """Histogram bin of every pixel, in the float32 arithmetic of ``torch.histc``.

    Args:
        depth_m: (H, W) float32 depth in metres; 0 (invalid), negative values and depth
            beyond ``max_range_m`` are not counted.
        config: simulator parameters.

    Returns:
        (H, W) int64: the bin in ``[0, bins)``, ``bins`` for depth exactly at the range's
        closed end (it joins the last bin), ``bins + 1`` for pixels not counted.

    Raises:
        ValueError: NaN or infinite depth.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    if not np.isfinite(depth).all():
        raise ValueError("depth_m has NaN or infinite values; mark invalid pixels with 0.0")
    bins = config.num_bins
    max_range = np.float32(config.max_range_m)
    if math.frexp(float(max_range))[0] == 0.5:
        # Dividing by a power of two is exact, so one product gives the same float32.
        scaled = depth * np.float32(bins / float(max_range))
    else:
        scaled = (depth * np.float32(bins)) / max_range
    index = np.clip(scaled, -1.0, bins + 1.0).astype(np.int64)  # truncation toward zero
    index[(depth <= 0) | (depth > max_range)] = bins + 1
    return index


def zone_depth_histograms(depth_m: np.ndarray, rects: np.ndarray,
                          config: SimulatorConfig) -> np.ndarray:
    """(Z, bins) float32 pixel counts of each zone's depth per bin.

    Args:
        depth_m: (H, W) depth in metres, 0 = invalid pixel.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels; a pixel belongs to a
            zone when its centre lies inside (rectangles may overlap or leave the image).
        config: simulator parameters.
    """
    index = depth_bins(depth_m, config)
    bins = config.num_bins
    bounds = zone_rects_to_pixel_bounds(rects, *index.shape)
    out = np.zeros((len(bounds), bins), dtype=np.float32)
    for zone, (y0, x0, y1, x1) in enumerate(bounds):
        counts = np.bincount(index[y0:y1, x0:x1].ravel(), minlength=bins + 2)
        out[zone] = counts[:bins]
        out[zone, bins - 1] += counts[bins]
    return out


def strongest_run(counts: np.ndarray) -> np.ndarray:
    """Keep only the run of consecutive non-empty bins with the largest total count.

    Args:
        counts: (Z, bins) non-negative counts.

    Returns:
        (Z, bins) counts, zero outside each zone's strongest run (the first one on ties);
        all zero for a zone with no counts.
    """
    nonzero = counts > 0
    previous = np.zeros_like(nonzero)
    previous[:, 1:] = nonzero[:, :-1]
    run_id = np.cumsum(nonzero & ~previous, axis=-1) * nonzero  # 0 = empty bin
    zones, bins = counts.shape
    run_sum = np.zeros((zones, bins + 1), dtype=np.float64)
    rows = np.repeat(np.arange(zones), bins)
    np.add.at(run_sum, (rows, run_id.ravel()), counts.astype(np.float64).ravel())
    run_sum[:, 0] = -1.0  # the empty bins never win
    best = np.argmax(run_sum, axis=-1)[:, None]  # first maximum on ties
    return np.where(run_id == best, counts, 0).astype(counts.dtype)


def simulate_zone_frame(depth_m: np.ndarray, rects: np.ndarray,
                        config: SimulatorConfig | None = None,
                        timestamp_s: float | None = None) -> ZoneFrame:
    """Simulate one sensor reading as a ``ZoneFrame``.

    Args:
        depth_m: (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels, row-major over the
            zone grid as it appears in the image; Z = 16 (4x4) or 64 (8x8).
        config: simulator parameters; ``SimulatorConfig()`` when None.
        timestamp_s: optional capture time stored in the frame, seconds.

    Returns:
        A ``ZoneFrame`` with mean and sigma (metres), validity and the no-target flag per
        zone, and the raw per-zone histogram (``hist_counts`` (n, n, bins) float32 pixel
        counts, ``hist_edges_m`` (bins + 1,) float32 metres).

    Raises:
        ValueError: a ``depth_m`` that is not a 2-D float map or holds NaN / infinite
            values; ``rects`` not (16, 4) or (64, 4), or not finite.
    """
    cfg = config or SimulatorConfig()
    depth = np.asarray(depth_m)
    boxes = np.asarray(rects, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be a single (H, W) map, got shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating) or depth.size == 0:
        raise ValueError(f"depth_m must be a non-empty float map, got dtype {depth.dtype} "
                         f"and shape {depth.shape}")
    if boxes.ndim != 2 or boxes.shape[0] not in (16, 64) or boxes.shape[1] != 4:
        raise ValueError(f"rects must have shape (16, 4) or (64, 4), got {boxes.shape}")
    if not np.isfinite(boxes).all():
        raise ValueError("rects has NaN or infinite values")
    depth = depth.astype(np.float32, copy=False)
    histogram = zone_depth_histograms(depth, boxes, cfg)
    edges = np.arange(cfg.num_bins + 1, dtype=np.float64) * cfg.bin_width_m
    centres = (edges[1:] + edges[:-1]) / 2
    cleaned = histogram.copy()
    cleaned[:, : cfg.ignored_bins] = 0.0
    cleaned = np.maximum(cleaned - np.float32(cfg.noise_floor_counts), np.float32(0.0))
    cluster = strongest_run(cleaned)
    weights = cluster.astype(np.float64)
    total = weights.sum(-1)
    valid = total > 0
    safe_total = np.where(valid, total, 1.0)
    mean = (weights * centres).sum(-1) / safe_total
    variance = (weights * (centres - mean[:, None]) ** 2).sum(-1) / safe_total
    mean = np.where(valid, mean, 0.0).astype(np.float32)
    sigma = np.where(valid, np.sqrt(variance), 0.0).astype(np.float32)
    # No target: an invalid zone with more of its pixels beyond the range than within.
    no_target = np.zeros(len(boxes), dtype=bool)
    bounds = zone_rects_to_pixel_bounds(boxes, *depth.shape)
    limit = np.float32(cfg.max_range_m)
    in_range = histogram.sum(-1)
    for zone in np.flatnonzero(~valid):
        y0, x0, y1, x1 = bounds[zone]
        no_target[zone] = np.count_nonzero(depth[y0:y1, x0:x1] > limit) > in_range[zone]
    grid = round(math.sqrt(len(boxes)))
    return ZoneFrame(mean_m=mean.reshape(grid, grid), sigma_m=sigma.reshape(grid, grid),
                     valid=valid.reshape(grid, grid), no_target=no_target.reshape(grid, grid),
                     hist_edges_m=edges.astype(np.float32),
                     hist_counts=histogram.reshape(grid, grid, -1), timestamp_s=timestamp_s,
                     sensor_model="simulated")
