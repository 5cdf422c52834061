"""Per-zone depth histograms of a batch of depth maps, the first step of the zone
simulator (:mod:`deltar.sensor.simulate`).

The depth of each zone's pixels is histogrammed in ``bin_width_m`` bins over ``[0,
max_range_m]`` with the float32 arithmetic of ``torch.histc`` (as the official release
does): depth beyond the range is left out, depth exactly at ``max_range_m`` falls into
the last bin. :func:`zone_histograms` does it in one pass over the pixels for all zones
(PyTorch ``bincount``, or the numba kernels of :mod:`deltar.sensor.compiled`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from deltar.sensor import compiled as compiled_kernels
from deltar.sensor.simulator_config import SimulatorConfig


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
    compiled = use_compiled(compiled, depth_m)
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
    # searchsorted wants contiguous values (it copies and warns otherwise): the row and
    # column indices of every frame, materialised rather than expanded.
    rows = pixels[:height].expand(batch, height).contiguous()
    cols = pixels[:width].expand(batch, width).contiguous()
    # Cell of every row / column: the number of bounds at or before it, minus one.
    row_cell = torch.searchsorted(row_bounds, rows, right=True) - 1
    col_cell = torch.searchsorted(col_bounds, cols, right=True) - 1
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


def use_compiled(compiled: bool | None, depth_m: torch.Tensor) -> bool:
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
