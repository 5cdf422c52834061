"""Compiled (numba) kernels for the zone simulator, when numba is installed.

:func:`~deltar.sensor.simulate.simulate_zones` counts every pixel of a frame into
(cell, bin) slots, sums each zone's cells and keeps each zone's strongest cluster. In
PyTorch that takes several full-frame passes (bin index, key sums, the not-counted mask,
a ``bincount``) and many small tensor operations; the kernels here do each step in one
loop with the same float32 bin arithmetic, so counts and clusters are identical and the
moments equal to float rounding. They need ``numba`` (the ``fast`` extra); without it
the PyTorch path runs.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import numpy as np


@functools.cache
def kernels() -> SimpleNamespace | None:
    """The compiled functions (``count_cells``, ``sum_zones``, ``cluster_moments``), or
    None when numba is not installed. Compiled on first use (about a second per
    function), once per process.
    """
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(nogil=True, cache=False)
    def count_cells(depth, row_base, col_base, factor, max_range, divide, bins, counts):
        # Returns the number of NaN or infinite pixels (which the caller refuses): one
        # test on the pixels already skipped, cheaper than a separate pass.
        height, width = depth.shape
        top = np.float32(bins + 1)
        not_finite = 0
        for i in range(height):
            base = row_base[i]
            for j in range(width):
                d = depth[i, j]
                if not d > 0 or d > max_range:  # invalid, NaN, or beyond the range
                    if d != d or d == np.inf or d == -np.inf:
                        not_finite += 1
                    continue
                scaled = (d * factor) / max_range if divide else d * factor
                if scaled > top:
                    scaled = top
                index = int(scaled)  # truncation toward zero, as the PyTorch path
                counts[base + col_base[j] + index] += 1
        return not_finite

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


    return SimpleNamespace(count_cells=count_cells, sum_zones=sum_zones,
                           cluster_moments=cluster_moments)


def _kernels() -> SimpleNamespace:
    found = kernels()
    if found is None:
        raise RuntimeError("the compiled simulator needs numba: pip install 'deltar[fast]'")
    return found


def cell_counts(depth_m: np.ndarray, row_base: np.ndarray, col_base: np.ndarray,
                per_frame: int, bins: int, max_range_m: float) -> np.ndarray:
    """(B, per_frame) int64 (cell, slot) pixel counts of a batch of depth maps.

    Args:
        depth_m: (B, H, W) float32 depth in metres; pixels <= 0 or beyond ``max_range_m``
            are not counted.
        row_base: (B, H) int64 offset of each row's cells (cell row x cells per row x slots).
        col_base: (B, W) int64 offset of each column's cell (cell column x slots).
        per_frame: cells x slots of one frame.
        bins: histogram bins; slot ``bins`` of a cell holds depth exactly at the range.
        max_range_m: upper end of the histogram, metres.

    Raises:
        RuntimeError: numba is not installed (check :func:`kernels` first).
        ValueError: a depth value is NaN or infinite.
    """
    count = _kernels().count_cells
    max_range = np.float32(max_range_m)
    divide = np.frexp(max_range)[0] != 0.5
    # The float32 arithmetic of the PyTorch path: depth * (bins / range) when the range
    # is a power of two (exact), else (depth * bins) / range.
    factor = np.float32(bins) if divide else np.float32(bins / float(max_range))
    depth = np.ascontiguousarray(depth_m, dtype=np.float32)
    counts = np.zeros((depth.shape[0], per_frame), dtype=np.int64)
    for frame in range(depth.shape[0]):
        if count(depth[frame], row_base[frame], col_base[frame], factor, max_range,
                 bool(divide), int(bins), counts[frame]):
            raise ValueError("depth_m has NaN or infinite values; mark invalid pixels with 0.0")
    return counts


def zone_sums(cells: np.ndarray, row_start: np.ndarray, row_stop: np.ndarray,
              col_start: np.ndarray, col_stop: np.ndarray) -> np.ndarray:
    """(B, Z, bins) float32 zone histograms: each zone's sum over its cells.

    Args:
        cells: (B, Ny, Nx, bins + 1) int64 cell counts (the last slot: depth exactly at
            the range, added to the last bin).
        row_start, row_stop, col_start, col_stop: (B, Z) int64 half-open cell ranges.
    """
    out = np.zeros((*row_start.shape, cells.shape[3] - 1), dtype=np.float32)
    _kernels().sum_zones(cells, row_start, row_stop, col_start, col_stop, out)
    return out


def cluster_moments(histogram: np.ndarray, ignored_bins: int, noise_floor: float,
                    centres_m: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each zone's strongest cluster and its moments.

    Args:
        histogram: (B, Z, bins) float32 zone histograms.
        ignored_bins: leading bins zeroed first.
        noise_floor: counts subtracted from every bin, clipped at 0.
        centres_m: (bins,) bin centres, metres.

    Returns:
        ``(mean, sigma, valid, cluster)``: (B, Z) float32 metres, (B, Z) float32 metres,
        (B, Z) bool, (B, Z, bins) float32 counts of the kept run.
    """
    hist = np.ascontiguousarray(histogram, dtype=np.float32)
    cluster = np.zeros_like(hist)
    mean = np.zeros(hist.shape[:-1], np.float32)
    sigma = np.zeros(hist.shape[:-1], np.float32)
    valid = np.zeros(hist.shape[:-1], bool)
    _kernels().cluster_moments(hist, int(ignored_bins), np.float32(noise_floor),
                               np.asarray(centres_m, dtype=np.float64), cluster, mean, sigma,
                               valid)
    return mean, sigma, valid, cluster
