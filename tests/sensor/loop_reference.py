"""Plain per-zone reference of the zone simulator, for tests and the benchmark.

Deliberately simple and independent of ``deltar.sensor.simulate``: one zone at a time,
``torch.histc`` for the histogram and ``numpy`` run splitting for the clusters, the way
the official release's NYU loader does it.
"""

from __future__ import annotations

import math

import numpy as np
import torch


def simulate_zones_loop(depth_m: np.ndarray, rects: np.ndarray, bin_width_m: float = 0.04,
                        max_range_m: float = 4.0, ignored_bins: int = 1,
                        noise_floor_counts: float = 20.0) -> tuple[np.ndarray, ...]:
    """Simulate zones one by one.

    Args:
        depth_m: (H, W) depth in metres, 0 = invalid.
        rects: (Z, 4) rectangles (y0, x0, y1, x1) in pixels.

    Returns:
        mean (Z,), sigma (Z,), valid (Z,) and raw histograms (Z, bins) as numpy arrays.
    """
    height, width = depth_m.shape
    bins = round(max_range_m / bin_width_m)
    edges = np.arange(bins + 1) * bin_width_m
    centres = (edges[1:] + edges[:-1]) / 2
    depth = torch.from_numpy(np.asarray(depth_m, dtype=np.float32))
    means, sigmas, valids, hists = [], [], [], []
    for y0, x0, y1, x1 in np.asarray(rects, dtype=np.float64):
        top, bottom = min(max(math.ceil(y0), 0), height), min(max(math.ceil(y1), 0), height)
        left, right = min(max(math.ceil(x0), 0), width), min(max(math.ceil(x1), 0), width)
        patch = depth[top:bottom, left:right].reshape(-1)
        patch = patch[patch > 0]
        raw = torch.histc(patch, bins=bins, min=0, max=max_range_m) if patch.numel() \
            else torch.zeros(bins)
        hist = raw.numpy().astype(np.float64)
        hist[:ignored_bins] = 0
        hist = np.clip(hist - noise_floor_counts, 0, None)
        nonzero = np.flatnonzero(hist)
        kept = np.zeros_like(hist)
        if nonzero.size:
            runs = np.split(nonzero, np.flatnonzero(np.diff(nonzero) != 1) + 1)
            best = runs[int(np.argmax([hist[run].sum() for run in runs]))]
            kept[best] = hist[best]
        total = kept.sum()
        if total > 0:
            mean = (kept * centres).sum() / total
            sigma = math.sqrt((kept * (centres - mean) ** 2).sum() / total)
        else:
            mean = sigma = 0.0
        means.append(mean)
        sigmas.append(sigma)
        valids.append(total > 0)
        hists.append(raw.numpy())
    return (np.array(means, dtype=np.float32), np.array(sigmas, dtype=np.float32),
            np.array(valids, dtype=bool), np.stack(hists).astype(np.float32))
