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
   pixels lie beyond the range than within it;
5. with ``max_targets`` > 1, report the other clusters as further targets, as ST's
   multi-target driver would (:func:`secondary_targets`, shared with the batched
   simulator).
"""

from __future__ import annotations

import math

import numpy as np

from deltar.sensor.geometry import zone_rects_to_pixel_bounds
from deltar.sensor.simulator_config import SimulatorConfig
from deltar.sensor.zone_frame import ZoneFrame

__all__ = ["depth_bins", "secondary_targets", "simulate_zone_frame", "strongest_run",
           "zone_depth_histograms"]

#: Most targets per zone the simulator reports, as ST's driver (1 to 4).
MAX_SIMULATED_TARGETS = 4


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


def secondary_targets(cleaned: np.ndarray, primary: np.ndarray, centres_m: np.ndarray,
                      separation_m: float, count: int, order: str = "strongest"
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The targets a zone reports besides its primary one, from its cleaned histogram.

    Shared by both simulators (:func:`simulate_zone_frame` and
    :func:`deltar.sensor.simulate.simulate_zones`), so their targets agree. Per zone:

    1. the runs of consecutive non-empty bins, each with its count-weighted mean;
    2. runs whose mean lies less than ``separation_m`` from the primary run's are part
       of the primary target (the sensor reports surfaces closer than that as one);
    3. the remaining runs, taken by increasing distance, join the current group while
       their mean lies less than ``separation_m`` from the group's count-weighted mean,
       else start a new group;
    4. the groups ordered by total count (``"strongest"``, the closer one first on
       ties) or by distance (``"closest"``); the first ``count`` are reported, each with
       the count-weighted mean and population standard deviation of its bins' centres.

    Args:
        cleaned: (N, bins) float32 counts after the ignored bins and the noise floor.
        primary: (N, bins) counts of each zone's primary (strongest) run, zero elsewhere.
        centres_m: (bins,) bin centres, metres.
        separation_m: smallest distance between two reported targets, metres.
        count: number of target slots to fill besides the primary (>= 0).
        order: ``"strongest"`` or ``"closest"``.

    Returns:
        ``(mean, sigma, valid, counts)``: (N, count) float32 metres, (N, count) float32
        metres (0 where not valid), (N, count) bool, and (N, count) float32 the targets'
        total counts (their pixels).
    """
    zones = cleaned.shape[0]
    mean_out = np.zeros((zones, count), dtype=np.float32)
    sigma_out = np.zeros((zones, count), dtype=np.float32)
    valid_out = np.zeros((zones, count), dtype=bool)
    counts_out = np.zeros((zones, count), dtype=np.float32)
    if count == 0 or zones == 0:
        return mean_out, sigma_out, valid_out, counts_out
    centres = np.asarray(centres_m, dtype=np.float64)
    nonzero = cleaned > 0
    previous = np.zeros_like(nonzero)
    previous[:, 1:] = nonzero[:, :-1]
    run_id = np.cumsum(nonzero & ~previous, axis=-1) * nonzero  # 0 = empty bin
    runs = int(run_id.max()) + 1
    weights = np.where(nonzero, cleaned, 0).astype(np.float64)
    run_total, run_first, run_mean, exists = _weighted_means(run_id, weights, centres, runs)
    # The primary run: the one holding the primary cluster's bins.
    has_primary = (primary > 0).any(axis=-1)
    primary_id = np.where(has_primary, run_id[np.arange(zones), np.argmax(primary > 0, -1)], 0)
    primary_mean = run_mean[np.arange(zones), primary_id]
    eligible = exists & has_primary[:, None] & (
        np.abs(run_mean - primary_mean[:, None]) >= separation_m)
    eligible[np.arange(zones), primary_id] = False
    # Group the eligible runs by increasing distance (run ids follow the bins).
    group = np.zeros((zones, runs), dtype=np.int64)  # 0 = no group
    current = np.zeros(zones, dtype=np.int64)
    group_total = np.zeros(zones)
    group_first = np.zeros(zones)
    for run in range(1, runs):
        take = eligible[:, run]
        if not take.any():
            continue
        group_mean = group_first / np.where(current > 0, group_total, 1.0)
        joins = take & (current > 0) & (run_mean[:, run] - group_mean < separation_m)
        starts = take & ~joins
        current = current + starts
        group_total = np.where(starts, 0.0, group_total) + np.where(take, run_total[:, run], 0)
        group_first = np.where(starts, 0.0, group_first) + np.where(take, run_first[:, run], 0)
        group[:, run] = np.where(take, current, 0)
    groups = int(current.max()) + 1
    if groups == 1:
        return mean_out, sigma_out, valid_out, counts_out
    bin_group = np.take_along_axis(group, run_id, axis=1)  # (N, bins), 0 = none
    total, _, mean, present = _weighted_means(bin_group, weights, centres, groups)
    spread = weights * (centres - np.take_along_axis(mean, bin_group, axis=1)) ** 2
    second = _sums_by_label(bin_group, spread, groups)
    sigma = np.sqrt(np.where(present, second / np.where(present, total, 1.0), 0.0))
    # Groups are numbered by distance: a stable sort keeps the closer first on ties.
    key = np.where(present, -total if order == "strongest" else mean, np.inf)
    ranked = np.argsort(key, axis=-1, kind="stable")[:, :count]
    chosen = np.take_along_axis(present, ranked, axis=1)
    width = ranked.shape[1]
    valid_out[:, :width] = chosen
    mean_out[:, :width] = np.where(chosen, np.take_along_axis(mean, ranked, axis=1), 0.0)
    sigma_out[:, :width] = np.where(chosen, np.take_along_axis(sigma, ranked, axis=1), 0.0)
    counts_out[:, :width] = np.where(chosen, np.take_along_axis(total, ranked, axis=1), 0.0)
    return mean_out, sigma_out, valid_out, counts_out


def target_signal(counts: np.ndarray, mean_m: np.ndarray, zone_pixels: np.ndarray
                  ) -> np.ndarray:
    """Simulated return signal of each target: its share of the zone's pixels over its
    squared distance (a return's signal falls with the square of the distance).

    Args:
        counts: (N, T) pixels of each target.
        mean_m: (N, T) target distances, metres (0: no target).
        zone_pixels: (N,) pixels of each zone with a depth in range.

    Returns:
        (N, T) float32 signal (0 where there is no target), in units of a zone filled by
        one surface at 1 m.
    """
    share = counts / np.asarray(zone_pixels, dtype=np.float64)[:, None]
    distance = np.asarray(mean_m, dtype=np.float64)
    return np.where(distance > 0, share / np.maximum(distance, 1e-6) ** 2, 0.0
                    ).astype(np.float32)


def _sums_by_label(labels: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """(N, count) sums of each row's ``values`` (N, bins) over the bins of each label
    0..count-1 (``labels`` (N, bins) int)."""
    rows = labels.shape[0]
    flat = (np.arange(rows)[:, None] * count + labels).ravel()
    return np.bincount(flat, values.ravel(), rows * count).reshape(rows, count)


def _weighted_means(labels: np.ndarray, weights: np.ndarray, centres: np.ndarray,
                    count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row and label 1..count-1 (0 = no label): the total weight, the weighted sum and
    the weighted mean of the bin centres (metres; 0 where empty) and whether any weight is
    there, each (N, count)."""
    total = _sums_by_label(labels, weights, count)
    first = _sums_by_label(labels, weights * centres, count)
    present = total > 0
    present[:, 0] = False
    return total, first, np.where(present, first / np.where(present, total, 1.0), 0.0), present


def check_target_options(max_targets: int, target_order: str) -> None:
    """Raise ``ValueError`` naming the argument unless ``max_targets`` is an integer in
    1..4 and ``target_order`` is ``"strongest"`` or ``"closest"``."""
    if isinstance(max_targets, (bool, np.bool_)) or not isinstance(
            max_targets, (int, np.integer)) or not 1 <= max_targets <= MAX_SIMULATED_TARGETS:
        raise ValueError(f"max_targets must be an integer in 1..{MAX_SIMULATED_TARGETS}, "
                         f"got {max_targets!r}")
    if target_order not in ("strongest", "closest"):
        raise ValueError(f"target_order must be 'strongest' or 'closest', got "
                         f"{target_order!r}")


def simulate_zone_frame(depth_m: np.ndarray, rects: np.ndarray,
                        config: SimulatorConfig | None = None,
                        timestamp_s: float | None = None, max_targets: int = 1,
                        target_order: str = "strongest") -> ZoneFrame:
    """Simulate one sensor reading as a ``ZoneFrame``.

    Args:
        depth_m: (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels, row-major over the
            zone grid as it appears in the image; Z = 16 (4x4) or 64 (8x8).
        config: simulator parameters; ``SimulatorConfig()`` when None.
        timestamp_s: optional capture time stored in the frame, seconds.
        max_targets: targets per zone to report, 1..4 (ST's
            ``VL53L5CX_NB_TARGET_PER_ZONE``). 1 (the default) gives the primary reading
            only, the frame has no target arrays. More fills ``target_mean_m``,
            ``target_sigma_m``, ``target_valid`` (n, n, max_targets): target 0 is the
            primary (strongest) cluster, the others come from
            :func:`secondary_targets` (``config.target_separation_m`` apart).
        target_order: order of targets 1.. (``"strongest"`` first, or ``"closest"``
            first); stored as the frame's ``target_order``.

    Returns:
        A ``ZoneFrame`` with mean and sigma (metres), validity and the no-target flag per
        zone, and the raw per-zone histogram (``hist_counts`` (n, n, bins) float32 pixel
        counts, ``hist_edges_m`` (bins + 1,) float32 metres).

    Raises:
        ValueError: a ``depth_m`` that is not a 2-D float map or holds NaN / infinite
            values; ``rects`` not (16, 4) or (64, 4), or not finite; ``max_targets`` not
            in 1..4 or an unknown ``target_order``.
    """
    cfg = config or SimulatorConfig()
    check_target_options(max_targets, target_order)
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
    targets = {}
    if max_targets > 1:
        more = secondary_targets(cleaned, cluster, centres, cfg.target_separation_m,
                                 max_targets - 1, target_order)
        pixels = np.maximum(histogram.sum(-1), 1.0)
        signal = target_signal(np.concatenate([total[:, None], more[3]], axis=1),
                               np.concatenate([mean[:, None], more[0]], axis=1), pixels)
        targets = {name: np.concatenate([first[:, None], rest], axis=1)
                   .reshape(grid, grid, max_targets)
                   for name, first, rest in zip(("target_mean_m", "target_sigma_m",
                                                 "target_valid"), (mean, sigma, valid),
                                                more[:3], strict=True)}
        targets["target_signal"] = signal.reshape(grid, grid, max_targets)
        targets["target_order"] = target_order
    return ZoneFrame(mean_m=mean.reshape(grid, grid), sigma_m=sigma.reshape(grid, grid),
                     valid=valid.reshape(grid, grid), no_target=no_target.reshape(grid, grid),
                     hist_edges_m=edges.astype(np.float32),
                     hist_counts=histogram.reshape(grid, grid, -1), timestamp_s=timestamp_s,
                     sensor_model="simulated", **targets)
