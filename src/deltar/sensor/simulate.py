"""Simulate multi-zone ToF readings (VL53L5CX-like) from a metric depth map.

Follows the simulation of the official DELTAR release (its NYU data loader), per zone:

1. histogram the ground-truth depth of the zone's pixels in ``bin_width_m`` bins over
   ``[0, max_range_m]`` (depth beyond the range is left out; a depth exactly at
   ``max_range_m`` falls into the last bin, as with ``torch.histc``);
2. zero the first ``ignored_bins`` bins (< 4 cm by default: invalid or too close);
3. subtract ``noise_floor_counts`` from every bin, clipping at zero;
4. split the non-empty bins into clusters of consecutive bins and keep only the cluster
   with the largest total count (the first one on ties);
5. report the count-weighted mean and (population) standard deviation of the kept
   bins' centres; a zone with no counts left is invalid.

Everything is vectorised over zones and over a batch of depth maps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from deltar.sensor import compiled as compiled_kernels
from deltar.sensor.zone_frame import ZoneFrame


@dataclass(frozen=True)
class SimulatorConfig:
    """Parameters of the zone simulator (defaults: the DELTAR paper and release).

    Attributes:
        bin_width_m: histogram bin width in metres (0.04).
        max_range_m: upper end of the histogram in metres (4.0); farther depth is not seen.
        ignored_bins: number of leading bins zeroed before clustering (1: depth < 4 cm).
        noise_floor_counts: counts subtracted from every bin, clipped at 0 (20 pixels).
    """

    bin_width_m: float = 0.04
    max_range_m: float = 4.0
    ignored_bins: int = 1
    noise_floor_counts: float = 20.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.bin_width_m) and self.bin_width_m > 0):
            raise ValueError(f"SimulatorConfig.bin_width_m must be > 0, got {self.bin_width_m}")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > self.bin_width_m):
            raise ValueError(f"SimulatorConfig.max_range_m must exceed bin_width_m, got "
                             f"{self.max_range_m}")
        ratio = self.max_range_m / self.bin_width_m
        if abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(f"SimulatorConfig.max_range_m ({self.max_range_m}) must be a "
                             f"whole number of bins of {self.bin_width_m} m")
        if not 0 <= self.ignored_bins < self.num_bins:
            raise ValueError(f"SimulatorConfig.ignored_bins must be in [0, {self.num_bins}), "
                             f"got {self.ignored_bins}")
        if not (math.isfinite(self.noise_floor_counts) and self.noise_floor_counts >= 0):
            raise ValueError(f"SimulatorConfig.noise_floor_counts must be >= 0, got "
                             f"{self.noise_floor_counts}")

    @property
    def num_bins(self) -> int:
        """Number of histogram bins (100 by default)."""
        return round(self.max_range_m / self.bin_width_m)

    def bin_edges_m(self) -> torch.Tensor:
        """(num_bins + 1,) float64 bin edges in metres, from 0 to ``max_range_m``."""
        return torch.arange(self.num_bins + 1, dtype=torch.float64) * self.bin_width_m


@dataclass
class SimulatedZones:
    """Simulated zone signals; ``B`` is absent for an unbatched call.

    Attributes:
        mean_m: (B, Z) float32 zone distance in metres (0 where invalid).
        sigma_m: (B, Z) float32 standard deviation in metres (0 where invalid).
        valid: (B, Z) bool, zones with signal left after the noise floor.
        histogram: (B, Z, bins) float32 raw per-zone pixel counts per depth bin (before
            ignoring bins and subtracting the noise floor).
        cluster: (B, Z, bins) float32 counts of the kept cluster after the noise floor
            (zero outside it); ``mean_m`` and ``sigma_m`` are its moments.
        bin_edges_m: (bins + 1,) float32 bin edges in metres.
        no_target: (B, Z) bool, invalid zones that would report *no target* (ST status
            255): more of their pixels with depth lie beyond ``max_range_m`` than within
            it. Invalid zones without it carry no information (e.g. no depth at all).
    """

    mean_m: torch.Tensor
    sigma_m: torch.Tensor
    valid: torch.Tensor
    histogram: torch.Tensor
    cluster: torch.Tensor
    bin_edges_m: torch.Tensor
    no_target: torch.Tensor


def zone_pixel_bounds(rects: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Torch twin of ``geometry.zone_rects_to_pixel_bounds`` (same semantics).

    Args:
        rects: (..., 4) float rectangles (y0, x0, y1, x1) in pixels.
        height, width: image size in pixels.

    Returns:
        (..., 4) int64 half-open pixel bounds clipped to the image; a pixel belongs to
        the zone when its centre lies in ``[y0, y1) x [x0, x1)``.
    """
    r = torch.ceil(rects.to(torch.float64))
    y0, y1 = r[..., 0].clamp(0, height), r[..., 2].clamp(0, height)
    x0, x1 = r[..., 1].clamp(0, width), r[..., 3].clamp(0, width)
    y1, x1 = torch.maximum(y1, y0), torch.maximum(x1, x0)
    return torch.stack([y0, x0, y1, x1], dim=-1).to(torch.int64)


def depth_bin_index(depth_m: torch.Tensor, config: SimulatorConfig) -> torch.Tensor:
    """Histogram bin of every depth value, ``bins`` (one past the last) where not counted.

    Uses the float32 arithmetic of ``torch.histc(depth, bins, 0, max_range_m)`` so that
    values on bin edges land in the same bin as in the official release.

    Args:
        depth_m: (...) depth in metres; 0 (invalid) and negative values are not counted,
            nor is depth beyond ``max_range_m``.
        config: simulator parameters.

    Returns:
        (...) int32 bin indices in ``[0, bins)``, or ``bins`` for values not counted.
    """
    depth = depth_m.to(torch.float32).contiguous()
    bins = config.num_bins
    index = _scaled_bin(depth, config)
    index.clamp_(0, bins)  # only for not-counted values, replaced below
    index.masked_fill_(index == bins, bins - 1)  # the last bin is closed, as in histc
    _mark_not_counted(index, depth, config, bins)
    return index


def _scaled_bin(depth: torch.Tensor, config: SimulatorConfig,
                out: torch.Tensor | None = None) -> torch.Tensor:
    """int32 ``trunc(depth * bins / max_range_m)`` in float32 arithmetic (histc's).

    For depth in ``(0, max_range_m]`` this is histc's bin, except ``bins`` at the closed
    upper end of the last bin (where histc takes ``bins - 1``). Values that are not
    counted get arbitrary indices: the caller overwrites them (:func:`_mark_not_counted`).

    Args:
        depth: (...) float32 depth in metres.
        config: simulator parameters.
        out: optional float32 buffer of ``depth``'s shape, reused for the result (as
            int32, same memory).

    Returns:
        (...) int32 indices.
    """
    max_range = float(np.float32(config.max_range_m))
    bins = config.num_bins
    if math.frexp(max_range)[0] == 0.5:
        # Dividing by a power of two is exact, so one product gives the same float32.
        scaled = torch.mul(depth, bins / max_range, out=out)
    else:
        scaled = torch.mul(depth, bins, out=out).div_(max_range)
    # Keeps the float-to-int conversion defined for infinite or huge values.
    scaled.clamp_(-1.0, bins + 1.0)
    # Converted in place (same element size): a fresh full-size tensor would cost more
    # than the arithmetic, mostly in page faults.
    index = scaled.view(torch.int32)
    index.copy_(scaled)  # truncation toward zero
    return index


def _mark_not_counted(index: torch.Tensor, depth: torch.Tensor, config: SimulatorConfig,
                      value: int) -> None:
    """Set ``index`` to ``value`` in place where depth is <= 0 or beyond ``max_range_m``.

    Args:
        index: (...) contiguous int32 tensor, modified in place.
        depth: (...) contiguous float32 depth in metres, same shape and device.
        config: simulator parameters.
        value: the index given to values that are not counted.
    """
    max_range = np.float32(config.max_range_m)
    if depth.device.type == "cpu":
        # numpy's comparisons and boolean assignment are several times faster here.
        depth_np = depth.detach().numpy()
        outside = depth_np <= 0
        outside |= depth_np > max_range
        index.numpy()[outside] = value
    else:
        outside = torch.le(depth, 0.0).logical_or_(torch.gt(depth, float(max_range)))
        index.masked_fill_(outside, value)


#: Most (frame, cell, bin) keys of one ``bincount`` in :func:`zone_histograms`.
_MAX_KEYS = 1 << 24
#: Interleaved copies of the cell histograms in :func:`zone_histograms`.
_LANES = 4


def _cell_boundaries(low: torch.Tensor, high: torch.Tensor, size: int) -> torch.Tensor:
    """Sorted distinct zone boundaries along one image axis, per frame.

    Args:
        low, high: (B, Z) int64 half-open zone bounds along the axis, in ``[0, size]``.
        size: image size along the axis, pixels.

    Returns:
        (B, N) int64: 0, every distinct bound, ``size``, ascending; frames with fewer
        distinct bounds are padded with ``size + 1`` (past every pixel).
    """
    batch = low.shape[0]
    ends = torch.tensor([0, size], dtype=torch.int64, device=low.device).expand(batch, 2)
    values = torch.cat([ends, low, high], dim=1).sort(dim=1).values
    repeated = torch.zeros_like(values, dtype=torch.bool)
    repeated[:, 1:] = values[:, 1:] == values[:, :-1]
    values = values.masked_fill(repeated, size + 1).sort(dim=1).values
    count = int((~repeated).sum(dim=1).max())
    return values[:, :count].contiguous()


def zone_histograms(depth_m: torch.Tensor, rects: torch.Tensor,
                    config: SimulatorConfig, compiled: bool | None = None) -> torch.Tensor:
    """Per-zone depth histograms of a batch: one pass over the pixels for all zones.

    The zone bounds cut each image into a grid of cells (rows between consecutive
    distinct row bounds, columns likewise; 9 x 9 cells for an 8x8 grid of abutting
    zones). One pass over the pixels histograms every cell (a ``bincount`` over (frame,
    cell, bin) keys, or the compiled kernel); a zone, being a rectangle of whole cells,
    is then the sum of its cells. Zones may overlap or leave the image.

    Args:
        depth_m: (B, H, W) depth in metres, 0 = invalid pixel.
        rects: (B, Z, 4) zone rectangles (y0, x0, y1, x1) in pixels.
        config: simulator parameters.
        compiled: count and sum the cells with the compiled kernels of
            :mod:`deltar.sensor.compiled` (numba, CPU tensors; identical counts); None
            uses them when numba is installed and the depth is on the CPU.

    Returns:
        (B, Z, bins) float32 pixel counts.

    Raises:
        ValueError: NaN or infinite depth (the compiled kernel tests each pixel as it
            counts; the PyTorch path sums the map first, element-wise only when that
            sum is not finite).
    """
    depth_m = depth_m.to(torch.float32).contiguous()
    compiled = _use_compiled(compiled, depth_m)
    if not compiled and not torch.isfinite(depth_m.sum()) and \
            not torch.isfinite(depth_m).all():
        raise ValueError("depth_m has NaN or infinite values; mark invalid pixels with 0.0")
    batch, height, width = depth_m.shape
    bins = config.num_bins
    # Per cell: the bins and one slot for depth exactly at max_range_m (merged into the
    # last bin at the end).
    slots = bins + 1
    y0, x0, y1, x1 = zone_pixel_bounds(rects, height, width).unbind(-1)  # (B, Z) each
    row_bounds = _cell_boundaries(y0, y1, height)  # (B, Ny)
    col_bounds = _cell_boundaries(x0, x1, width)  # (B, Nx)
    cells_y, cells_x = row_bounds.shape[1] - 1, col_bounds.shape[1] - 1
    per_frame = cells_y * cells_x * slots
    # Layouts with many distinct bounds make many cells: keep each bincount moderate
    # (and its keys within int32) by splitting the zones, then the batch.
    zones = rects.shape[1]
    if per_frame > _MAX_KEYS and zones > 1:
        half = zones // 2
        return torch.cat([zone_histograms(depth_m, rects[:, :half], config, compiled),
                          zone_histograms(depth_m, rects[:, half:], config, compiled)], dim=1)
    chunk = max(1, min(batch, _MAX_KEYS // per_frame))
    if chunk < batch:
        return torch.cat([zone_histograms(depth_m[i : i + chunk], rects[i : i + chunk], config,
                                          compiled)
                          for i in range(0, batch, chunk)])
    device = depth_m.device
    pixels = torch.arange(max(height, width), dtype=torch.int64, device=device)
    # Cell of every row / column: the number of bounds at or before it, minus one.
    row_cell = torch.searchsorted(row_bounds, pixels[:height].expand(batch, height),
                                  right=True) - 1
    col_cell = torch.searchsorted(col_bounds, pixels[:width].expand(batch, width),
                                  right=True) - 1
    if compiled:
        return _compiled_zone_histograms(depth_m, row_cell, col_cell, row_bounds, col_bounds,
                                         (y0, x0, y1, x1), (cells_y, cells_x, slots), config)
    counts = _cell_counts(depth_m, row_cell, col_cell, cells_x, per_frame, slots, config)
    # A zone's histogram sums the cells in its row range and column range: with 0/1
    # membership matrices, one batched product over the rows, then a weighted sum over
    # the columns. float32 is exact here: every partial sum is a whole number of
    # pixels below 2**24.
    cells = counts.to(torch.float32).reshape(batch, cells_y, cells_x * slots)
    row_in = _cell_membership(row_bounds, y0, y1)  # (B, Z, Ny)
    col_in = _cell_membership(col_bounds, x0, x1)  # (B, Z, Nx)
    by_rows = torch.bmm(row_in, cells).reshape(batch, -1, cells_x, slots)
    zone = torch.einsum("bzcs,bzc->bzs", by_rows, col_in)
    zone[..., bins - 1] += zone[..., bins]
    return zone[..., :bins].contiguous()


def _use_compiled(compiled: bool | None, depth_m: torch.Tensor) -> bool:
    """Whether to run the compiled kernels: as asked, or (None) when numba is installed
    and the depth is on the CPU; asking for them with a GPU tensor is an error."""
    if compiled is None:
        return depth_m.device.type == "cpu" and compiled_kernels.kernels() is not None
    if compiled and depth_m.device.type != "cpu":
        raise ValueError("the compiled simulator runs on CPU tensors only")
    return bool(compiled)


def _compiled_zone_histograms(depth_m: torch.Tensor, row_cell: torch.Tensor,
                              col_cell: torch.Tensor, row_bounds: torch.Tensor,
                              col_bounds: torch.Tensor, bounds: tuple[torch.Tensor, ...],
                              grid: tuple[int, int, int], config: SimulatorConfig
                              ) -> torch.Tensor:
    """(B, Z, bins) float32 zone histograms with the compiled kernels (CPU)."""
    cells_y, cells_x, slots = grid
    counts = compiled_kernels.cell_counts(
        depth_m.numpy(), (row_cell * cells_x * slots).numpy(), (col_cell * slots).numpy(),
        cells_y * cells_x * slots, config.num_bins, config.max_range_m)
    y0, x0, y1, x1 = bounds
    # Zone bounds are cell bounds: their positions in the sorted bounds are cell indices.
    rows = [torch.searchsorted(row_bounds, v.contiguous()).numpy() for v in (y0, y1)]
    cols = [torch.searchsorted(col_bounds, v.contiguous()).numpy() for v in (x0, x1)]
    cells = counts.reshape(counts.shape[0], cells_y, cells_x, slots)
    return torch.from_numpy(compiled_kernels.zone_sums(cells, *rows, *cols))


def _cell_counts(depth_m: torch.Tensor, row_cell: torch.Tensor, col_cell: torch.Tensor,
                 cells_x: int, per_frame: int, slots: int, config: SimulatorConfig
                 ) -> torch.Tensor:
    """(B, cells x slots) int64 counts of every frame with PyTorch (``bincount``)."""
    batch, height, width = depth_m.shape
    device = depth_m.device
    pixels = torch.arange(width, dtype=torch.int64, device=device)
    # Neighbouring pixels mostly share a key, and counting the same slot over and over
    # waits on the previous increment: columns take turns over _LANES copies of the
    # histogram, summed afterwards.
    lane = pixels[:width] % _LANES
    row_key = (row_cell * cells_x * slots).to(torch.int32)  # (B, H)
    col_key = (col_cell * slots + lane * per_frame).to(torch.int32)  # (B, W)
    dump = _LANES * per_frame  # one slot past every histogram, for pixels not counted
    # Frame by frame, in one reused buffer: a frame's pixels stay in the CPU cache
    # through all steps, and no full-size tensor is allocated per frame.
    buffer = torch.empty((height, width), dtype=torch.float32, device=device)
    counts = torch.empty(batch, per_frame, dtype=torch.int64, device=device)
    for index in range(batch):
        keys = _scaled_bin(depth_m[index], config, out=buffer)
        keys.add_(row_key[index, :, None]).add_(col_key[index, None, :])
        _mark_not_counted(keys, depth_m[index], config, dump)
        lanes = torch.bincount(keys.reshape(-1), minlength=dump + 1)[:dump]
        torch.sum(lanes.reshape(_LANES, per_frame), dim=0, out=counts[index])
    return counts


def _cell_membership(bounds: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(B, Z, N - 1) float32: 1 where cell ``[bounds[i], bounds[i + 1])`` lies in ``[low, high)``.

    Args:
        bounds: (B, N) int64 cell bounds from :func:`_cell_boundaries`.
        low, high: (B, Z) int64 zone bounds, each one of ``bounds``.
    """
    start = bounds[:, None, :-1]
    inside = (start >= low[..., None]) & (start < high[..., None])
    return inside.to(torch.float32)


def strongest_cluster(counts: torch.Tensor) -> torch.Tensor:
    """Keep only the run of consecutive non-empty bins with the largest total count.

    Args:
        counts: (..., bins) non-negative counts.

    Returns:
        (..., bins) counts, zero outside the strongest run (the first one on ties); all
        zero when ``counts`` is all zero.
    """
    nonzero = counts > 0
    previous = torch.nn.functional.pad(nonzero[..., :-1], (1, 0), value=False)
    run_start = nonzero & ~previous
    run_id = torch.cumsum(run_start.to(torch.int64), dim=-1) * nonzero  # 0 = empty bin
    run_sum = torch.zeros(*counts.shape[:-1], counts.shape[-1] + 1, dtype=torch.float64,
                          device=counts.device)
    run_sum.scatter_add_(-1, run_id, counts.to(torch.float64))
    run_sum[..., 0] = -1.0  # the empty bins never win
    best = torch.argmax(run_sum, dim=-1, keepdim=True)  # first maximum on ties
    return torch.where(run_id == best, counts, torch.zeros_like(counts))


def simulate_zones(depth_m: torch.Tensor | np.ndarray, rects: torch.Tensor | np.ndarray,
                   config: SimulatorConfig | None = None, compiled: bool | None = None
                   ) -> SimulatedZones:
    """Simulate the zone signals a multi-zone ToF sensor would report.

    Args:
        depth_m: (B, H, W) or (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (B, Z, 4) or (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels of the depth
            map; a (Z, 4) array is shared by the whole batch. Rectangles may run past the
            image: only the pixels inside count.
        config: simulator parameters; ``SimulatorConfig()`` when None.
        compiled: run the per-pixel counting, the zone sums and the cluster moments in
            the compiled kernels of :mod:`deltar.sensor.compiled` (numba, CPU; the same
            counts, moments equal to float rounding); None uses them when numba is
            installed and the depth is on the CPU.

    Returns:
        ``SimulatedZones`` with (B, Z) tensors, or (Z,) for an unbatched ``depth_m``, on
        ``depth_m``'s device.

    Raises:
        ValueError: wrong shapes, batch sizes that do not match, NaN or infinite values.
    """
    cfg = config or SimulatorConfig()
    depth = torch.as_tensor(depth_m)
    boxes = torch.as_tensor(rects)
    if depth.ndim not in (2, 3) or not depth.is_floating_point():
        raise ValueError(f"depth_m must be a float (B, H, W) or (H, W) map, got dtype "
                         f"{depth.dtype} and shape {tuple(depth.shape)}")
    if depth.numel() == 0:
        raise ValueError(f"depth_m is empty: shape {tuple(depth.shape)}")
    depth = depth.to(torch.float32)
    compiled = _use_compiled(compiled, depth)
    if boxes.ndim not in (2, 3) or boxes.shape[-1] != 4 or boxes.shape[-2] == 0:
        raise ValueError(f"rects must have shape (B, Z, 4) or (Z, 4), got {tuple(boxes.shape)}")
    if not torch.isfinite(boxes).all():
        raise ValueError("rects has NaN or infinite values")
    batched = depth.ndim == 3
    if not batched and boxes.ndim == 3:
        raise ValueError("rects is batched (B, Z, 4) but depth_m is a single (H, W) map")
    if not batched:
        depth = depth[None]
    if boxes.ndim == 2:
        boxes = boxes[None].expand(depth.shape[0], -1, -1)
    if boxes.shape[0] != depth.shape[0]:
        raise ValueError(f"rects has batch size {boxes.shape[0]} but depth_m has "
                         f"{depth.shape[0]}")
    boxes = boxes.to(depth.device)

    histogram = zone_histograms(depth, boxes, cfg, compiled)
    edges = cfg.bin_edges_m().to(depth.device)
    centres = (edges[1:] + edges[:-1]) / 2
    if compiled:
        moments = compiled_kernels.cluster_moments(histogram.numpy(), cfg.ignored_bins,
                                                   cfg.noise_floor_counts, centres.numpy())
        mean, sigma, valid, cluster = (torch.from_numpy(array) for array in moments)
    else:
        cleaned = histogram.clone()
        cleaned[..., : cfg.ignored_bins] = 0.0
        cleaned = (cleaned - cfg.noise_floor_counts).clamp(min=0.0)
        cluster = strongest_cluster(cleaned)
        weights = cluster.to(torch.float64)
        total = weights.sum(-1)
        valid = total > 0
        safe_total = torch.where(valid, total, torch.ones_like(total))
        mean = (weights * centres).sum(-1) / safe_total
        variance = (weights * (centres - mean[..., None]) ** 2).sum(-1) / safe_total
        mean = torch.where(valid, mean, 0.0).to(torch.float32)
        sigma = torch.where(valid, variance.sqrt(), 0.0).to(torch.float32)

    no_target = _no_target(depth, boxes, valid, histogram, cfg)
    out = SimulatedZones(mean_m=mean, sigma_m=sigma, valid=valid, histogram=histogram,
                         cluster=cluster, bin_edges_m=edges.to(torch.float32),
                         no_target=no_target)
    if not batched:
        for name in ("mean_m", "sigma_m", "valid", "histogram", "cluster", "no_target"):
            setattr(out, name, getattr(out, name)[0])
    return out


def _no_target(depth: torch.Tensor, rects: torch.Tensor, valid: torch.Tensor,
               histogram: torch.Tensor, config: SimulatorConfig) -> torch.Tensor:
    """(B, Z) bool: invalid zones with more pixels beyond the range than within it.

    Counted only for the invalid zones (few in most frames), from the depth map itself:
    the histogram holds the in-range pixels only.
    """
    candidates = torch.nonzero(~valid).tolist()
    if not candidates:
        return torch.zeros_like(valid)
    bounds = zone_pixel_bounds(rects, depth.shape[-2], depth.shape[-1]).tolist()
    in_range = histogram.sum(-1).tolist()
    limit = np.float32(config.max_range_m)
    # numpy slices cost a few microseconds each, torch's several times more.
    pixels = depth.cpu().numpy()
    flags = np.zeros(tuple(valid.shape), dtype=bool)
    for b, z in candidates:
        y0, x0, y1, x1 = bounds[b][z]
        flags[b, z] = np.count_nonzero(pixels[b, y0:y1, x0:x1] > limit) > in_range[b][z]
    return torch.from_numpy(flags).to(valid.device)


def simulate_zone_frame(depth_m: np.ndarray, rects: np.ndarray,
                        config: SimulatorConfig | None = None,
                        timestamp_s: float | None = None) -> ZoneFrame:
    """Simulate one sensor reading as a ``ZoneFrame``.

    Args:
        depth_m: (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels, row-major over the
            zone grid as it appears in the image; Z = 16 (4x4) or 64 (8x8).
        config: simulator parameters; ``SimulatorConfig()`` when None.
        timestamp_s: optional capture time stored in the frame.

    Returns:
        A ``ZoneFrame`` with mean, sigma, validity and the no-target flag per zone, and
        the raw per-zone histogram (``hist_counts``, ``hist_edges_m``).
    """
    depth = np.asarray(depth_m)
    boxes = np.asarray(rects, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be a single (H, W) map, got shape {depth.shape}")
    if boxes.ndim != 2 or boxes.shape[0] not in (16, 64):
        raise ValueError(f"rects must have shape (16, 4) or (64, 4), got {boxes.shape}")
    zones = simulate_zones(torch.from_numpy(depth.astype(np.float32)), torch.from_numpy(boxes),
                           config)
    return ZoneFrame(mean_m=zones.mean_m.numpy(), sigma_m=zones.sigma_m.numpy(),
                     valid=zones.valid.numpy(), no_target=zones.no_target.numpy(),
                     hist_edges_m=zones.bin_edges_m.numpy(),
                     hist_counts=zones.histogram.numpy(), timestamp_s=timestamp_s,
                     sensor_model="simulated")
