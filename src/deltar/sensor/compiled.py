"""A compiled (numba) kernel for the simulator's per-cell depth histograms, when available.

:func:`~deltar.sensor.simulate.zone_histograms` counts every pixel of a frame into
(cell, bin) slots. In PyTorch that takes several full-frame passes (bin index, key sums,
the not-counted mask, a ``bincount``); the kernel here does it in one pass per pixel with
the same float32 arithmetic, so the counts are identical. It needs ``numba`` (the
``fast`` extra); without it the PyTorch path runs.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np


@functools.cache
def cell_count_kernel() -> Callable | None:
    """The compiled counting function, or None when numba is not installed.

    Compiled on first use (about a second), once per process.
    """
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(nogil=True, cache=False)
    def count_cells(depth, row_base, col_base, factor, max_range, divide, bins, counts):
        height, width = depth.shape
        top = np.float32(bins + 1)
        for i in range(height):
            base = row_base[i]
            for j in range(width):
                d = depth[i, j]
                if not d > 0 or d > max_range:  # invalid, NaN, or beyond the range
                    continue
                scaled = (d * factor) / max_range if divide else d * factor
                if scaled > top:
                    scaled = top
                index = int(scaled)  # truncation toward zero, as the PyTorch path
                counts[base + col_base[j] + index] += 1

    return count_cells


def count_cells(depth_m: np.ndarray, row_base: np.ndarray, col_base: np.ndarray,
                bins: int, max_range_m: float, counts: np.ndarray) -> None:
    """Add one frame's pixels to ``counts`` in place (the compiled kernel).

    Args:
        depth_m: (H, W) float32 depth in metres; pixels <= 0 or beyond ``max_range_m``
            are not counted.
        row_base: (H,) int64 offset of each row's cells (cell row x cells per row x slots).
        col_base: (W,) int64 offset of each column's cell (cell column x slots).
        bins: histogram bins; slot ``bins`` of a cell holds depth exactly at the range.
        max_range_m: upper end of the histogram, metres.
        counts: (cells x (bins + 1),) int64 counts, added to.

    Raises:
        RuntimeError: numba is not installed (check :func:`cell_count_kernel` first).
    """
    kernel = cell_count_kernel()
    if kernel is None:
        raise RuntimeError("the compiled simulator needs numba: pip install 'deltar[fast]'")
    max_range = np.float32(max_range_m)
    divide = np.frexp(max_range)[0] != 0.5
    # The float32 arithmetic of the PyTorch path: depth * (bins / range) when the range
    # is a power of two (exact), else (depth * bins) / range.
    factor = np.float32(bins) if divide else np.float32(bins / float(max_range))
    kernel(np.ascontiguousarray(depth_m, dtype=np.float32), row_base, col_base, factor,
           max_range, bool(divide), int(bins), counts)


@functools.cache
def zone_kernels() -> tuple[Callable, Callable] | None:
    """The compiled zone-sum and cluster-moment functions, or None without numba."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(nogil=True, cache=False)
    def sum_zones(cells, row_start, row_stop, col_start, col_stop, out):
        # cells: (B, Ny, Nx, slots); zone z of frame b covers cell rows
        # [row_start, row_stop) and columns [col_start, col_stop); the extra last slot
        # (depth exactly at the range) joins the last bin.
        batch, zones = row_start.shape
        slots = cells.shape[3]
        bins = slots - 1
        for b in range(batch):
            for z in range(zones):
                for i in range(row_start[b, z], row_stop[b, z]):
                    for j in range(col_start[b, z], col_stop[b, z]):
                        for k in range(bins):
                            out[b, z, k] += cells[b, i, j, k]
                        out[b, z, bins - 1] += cells[b, i, j, bins]

    @numba.njit(nogil=True, cache=False)
    def cluster_moments(histogram, ignored, floor, centres, cluster, mean, sigma, valid):
        # The strongest run of consecutive non-empty bins after ignoring the first bins
        # and subtracting the noise floor (first maximum on ties), and its moments.
        batch, zones, bins = histogram.shape
        cleaned = np.zeros(bins, dtype=np.float32)
        for b in range(batch):
            for z in range(zones):
                for k in range(bins):
                    value = histogram[b, z, k] - floor if k >= ignored else np.float32(0.0)
                    cleaned[k] = value if value > 0 else np.float32(0.0)
                best_sum, best_start, best_stop = -1.0, 0, 0
                k = 0
                while k < bins:
                    if cleaned[k] > 0:
                        start, total = k, 0.0
                        while k < bins and cleaned[k] > 0:
                            total += np.float64(cleaned[k])
                            k += 1
                        if total > best_sum:
                            best_sum, best_start, best_stop = total, start, k
                    else:
                        k += 1
                if best_sum <= 0:
                    continue
                weight_sum, first = 0.0, 0.0
                for k in range(best_start, best_stop):
                    cluster[b, z, k] = cleaned[k]
                    weight_sum += np.float64(cleaned[k])
                    first += np.float64(cleaned[k]) * centres[k]
                centre = first / weight_sum
                second = 0.0
                for k in range(best_start, best_stop):
                    second += np.float64(cleaned[k]) * (centres[k] - centre) ** 2
                valid[b, z] = True
                mean[b, z] = centre
                sigma[b, z] = np.sqrt(second / weight_sum)

    return sum_zones, cluster_moments
