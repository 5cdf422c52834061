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
