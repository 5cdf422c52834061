"""Resampling between a feature map and the per-zone feature patches.

The zone grid of one sample is a ``n x n`` arrangement of rectangles in image pixels.
At a feature map of stride ``s`` its bounding window, in feature cells, is
``[trunc(min y0 / s), trunc(max y1 / s))`` (likewise in x; ``trunc`` rounds toward
zero, as the release does). That window, zero-padded where it runs past the map, is
resized bilinearly (``align_corners=True``) to ``(n * p_h, n * p_w)`` cells and cut
into ``n x n`` patches of ``p_h x p_w`` tokens, one per zone; ``p_h = ceil(int(max
zone height px) / s)``. The reverse resize puts per-zone results back into the map.

Both resizes are separable linear maps, so they are built as small per-sample
matrices (rows x rows and cols x cols) and applied with two batched matrix products:
every sample of a batch may have its own zone layout, and zones may lie partly or
wholly outside the image.

The matrices are built with an in-place ``index_add_``, which the TorchScript tracer
(ONNX export) drops; ``traceable=True`` builds them with an equivalent one-hot product
instead (same values, more memory), see :meth:`deltar.models.DeltarNet.set_traceable`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ZoneWindow:
    """Where the zone grid lies in one feature map, for every sample of a batch.

    Attributes:
        start: (B, 2) int64 first row and column of the window, in feature cells
            (may be negative: the window may start above or left of the map).
        length: (B, 2) int64 window height and width in cells (at least 1).
        patch: (p_h, p_w) tokens per zone patch (shared by the batch).
        grid: zones per side n.
    """

    start: torch.Tensor
    length: torch.Tensor
    patch: tuple[int, int]
    grid: int


def zone_window(zone_rects: torch.Tensor, stride: float, grid: int) -> ZoneWindow:
    """Locate each sample's zone grid in a feature map of the given stride.

    Args:
        zone_rects: (B, Z, 4) float (y0, x0, y1, x1) zone rectangles in input-image
            pixels, Z = grid * grid, row-major.
        stride: input pixels per feature cell (e.g. 4.0 for a 1/4 map).
        grid: zones per side n.

    Returns:
        The :class:`ZoneWindow` (the patch size is the largest over the batch).
    """
    rects = zone_rects.detach().float()
    scaled = rects / stride
    # ``trunc`` (toward zero), not ``floor``: the release casts to int32 here.
    start = _trunc(torch.stack([scaled[..., 0].amin(1), scaled[..., 1].amin(1)], dim=1))
    end = _trunc(torch.stack([scaled[..., 2].amax(1), scaled[..., 3].amax(1)], dim=1))
    length = (end - start).clamp_min(1)
    max_height_px = int((rects[..., 2] - rects[..., 0]).amax().item())
    max_width_px = int((rects[..., 3] - rects[..., 1]).amax().item())
    patch = (
        max(1, math.ceil(max_height_px / stride)),
        max(1, math.ceil(max_width_px / stride)),
    )
    return ZoneWindow(start.long(), length.long(), patch, grid)


def _trunc(values: torch.Tensor) -> torch.Tensor:
    """Round toward zero: exactly ``values.trunc()``, written with operators that export
    to ONNX (``aten::trunc`` has no ONNX symbolic)."""
    return torch.sign(values) * torch.floor(torch.abs(values))


def _linear_resize_weights(
    in_size: torch.Tensor, out_size: torch.Tensor, num_out: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bilinear ``align_corners=True`` taps for resizing each of B lines.

    Args:
        in_size: (B,) int64 input lengths.
        out_size: (B,) int64 output lengths.
        num_out: number of output samples to compute (>= every ``out_size``).

    Returns:
        (low, high, weight_high), each (B, num_out): the two input indices each
        output sample reads and the weight of ``high`` (``low`` gets ``1 - weight``).
    """
    in_f = in_size.to(torch.float32)[:, None]
    out_f = out_size.to(torch.float32)[:, None]
    out_index = torch.arange(num_out, dtype=torch.float32, device=in_size.device)[None, :]
    # Same float32 arithmetic as torch's upsampling: source = scale * index, with
    # scale = (in - 1) / (out - 1), or 0 when the output has a single sample.
    scale = torch.where(out_f > 1, (in_f - 1.0) / (out_f - 1.0).clamp_min(1.0), 0.0)
    source = scale * out_index
    low = source.floor()
    weight_high = source - low
    low = low.long()
    high = torch.minimum(low + 1, (in_size[:, None] - 1).clamp_min(0))
    return low, high, weight_high


def _scatter_rows(
    rows: int, cols: int, row_index: torch.Tensor, col_index: torch.Tensor, weight: torch.Tensor,
    traceable: bool = False,
) -> torch.Tensor:
    """Dense (B, rows, cols) matrix with ``weight`` added at (row_index, col_index).

    Entries whose column index falls outside ``[0, cols)`` are dropped (they read the
    zero padding outside the map). ``traceable`` builds the same matrix as a one-hot
    product, which the ONNX tracer records (it drops the in-place ``index_add_``).
    """
    if traceable:
        row_hot = row_index[..., None] == torch.arange(rows, device=weight.device)
        col_hot = col_index[..., None] == torch.arange(cols, device=weight.device)
        return torch.einsum("bj,bjr,bjc->brc", weight, row_hot.to(weight.dtype),
                            col_hot.to(weight.dtype))
    batch = weight.shape[0]
    inside = (col_index >= 0) & (col_index < cols)
    matrix = torch.zeros(batch, rows, cols, dtype=weight.dtype, device=weight.device)
    flat = (
        torch.arange(batch, device=weight.device)[:, None] * rows * cols
        + row_index * cols
        + col_index.clamp(0, cols - 1)
    )
    matrix.view(-1).index_add_(0, flat[inside], weight[inside])
    return matrix


def gather_matrix(start: torch.Tensor, length: torch.Tensor, out_size: int, map_size: int,
                  traceable: bool = False):
    """Matrix taking map rows to window rows resized to ``out_size`` (zeros outside).

    Args:
        start: (B,) first window row in map cells (may be negative).
        length: (B,) window length in cells.
        out_size: resized window length (n * p).
        map_size: map length in cells.
        traceable: build it with ONNX-traceable operators (same values).

    Returns:
        (B, out_size, map_size) float32 matrix.
    """
    fixed_out = torch.full_like(length, out_size)
    low, high, weight_high = _linear_resize_weights(length, fixed_out, out_size)
    out_rows = torch.arange(out_size, device=start.device).expand_as(low)
    first = _scatter_rows(out_size, map_size, out_rows, start[:, None] + low, 1.0 - weight_high,
                          traceable)
    second = _scatter_rows(out_size, map_size, out_rows, start[:, None] + high, weight_high,
                           traceable)
    return first + second


def scatter_matrix(start: torch.Tensor, length: torch.Tensor, patch_size: int, map_size: int,
                   traceable: bool = False):
    """Matrix taking resized window rows back to map rows (the reverse resize).

    Args:
        start: (B,) first window row in map cells (may be negative).
        length: (B,) window length in cells.
        patch_size: resized window length (n * p).
        map_size: map length in cells.
        traceable: build it with ONNX-traceable operators (same values).

    Returns:
        (B, map_size, patch_size) float32 matrix; map rows outside the window are 0.
    """
    max_length = int(length.max().item())
    fixed_in = torch.full_like(length, patch_size)
    low, high, weight_high = _linear_resize_weights(fixed_in, length, max_length)
    window_rows = torch.arange(max_length, device=start.device).expand_as(low)
    map_rows = start[:, None] + window_rows
    # Rows beyond a sample's own window length, or outside the map, receive nothing.
    keep = (window_rows < length[:, None]) & (map_rows >= 0) & (map_rows < map_size)
    map_rows = torch.where(keep, map_rows, torch.full_like(map_rows, -1))
    low_w = torch.where(keep, 1.0 - weight_high, torch.zeros_like(weight_high))
    high_w = torch.where(keep, weight_high, torch.zeros_like(weight_high))
    # Build the transposed problem (patch rows as "columns") and flip it.
    first = _scatter_rows(patch_size, map_size, low, map_rows, low_w, traceable)
    second = _scatter_rows(patch_size, map_size, high, map_rows, high_w, traceable)
    return (first + second).transpose(1, 2)


class ZonePatchResampler:
    """Cuts zone patches out of a feature map and pastes per-zone results back.

    Args:
        window: the :class:`ZoneWindow` of this feature map.
        map_size: (H, W) of the feature map in cells.
        dtype: dtype of the features.
        traceable: build the resampling matrices with ONNX-traceable operators (same
            values; for export).
    """

    def __init__(self, window: ZoneWindow, map_size: tuple[int, int], dtype: torch.dtype,
                 traceable: bool = False) -> None:
        self.window = window
        n = window.grid
        p_h, p_w = window.patch
        start, length = window.start, window.length
        height, width = map_size
        self.rows_in = gather_matrix(start[:, 0], length[:, 0], n * p_h, height,
                                     traceable).to(dtype)
        self.cols_in = gather_matrix(start[:, 1], length[:, 1], n * p_w, width,
                                     traceable).to(dtype)
        self.rows_out = scatter_matrix(start[:, 0], length[:, 0], n * p_h, height,
                                       traceable).to(dtype)
        self.cols_out = scatter_matrix(start[:, 1], length[:, 1], n * p_w, width,
                                       traceable).to(dtype)

    def gather(self, feature_map: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) map -> (B * Z, p_h * p_w, C) zone patch tokens (zones row-major)."""
        resized = self.rows_in[:, None] @ feature_map @ self.cols_in.transpose(1, 2)[:, None]
        n = self.window.grid
        p_h, p_w = self.window.patch
        batch, channels = resized.shape[:2]
        tokens = resized.reshape(batch, channels, n, p_h, n, p_w)
        return tokens.permute(0, 2, 4, 3, 5, 1).reshape(batch * n * n, p_h * p_w, channels)

    def scatter(self, patches: torch.Tensor, batch: int) -> torch.Tensor:
        """(B * Z, p_h * p_w, C) zone patch tokens -> (B, C, H, W) map (0 outside the zones)."""
        n = self.window.grid
        p_h, p_w = self.window.patch
        channels = patches.shape[-1]
        grid = patches.reshape(batch, n, n, p_h, p_w, channels)
        grid = grid.permute(0, 5, 1, 3, 2, 4).reshape(batch, channels, n * p_h, n * p_w)
        return self.rows_out[:, None] @ grid @ self.cols_out.transpose(1, 2)[:, None]
