"""The network's depth made to reproduce each zone's reading: the zone-consistency step.

A zone reports the mean of the strongest cluster of the depths in its footprint (one
target, as the sensor reports it: :mod:`deltar.sensor.simulate_frame`), yet nothing in
the network makes its depth average back to that reading. This step measures, for each
valid zone, the ratio of its reading to the mean of the network's depth over the
footprint's cells that lie on the reported target (within :data:`WINDOW_SIGMAS` of the
zone's sigma, at least :data:`WINDOW_RELATIVE` of its reading), spreads the log ratios
between the zone centres (bilinearly; a zone without a ratio takes its neighbours'
mean, the image beyond the grid its nearest zones') and multiplies the depth by
``exp(strength * field)``. ``strength`` is part of the output contract
(``zone_consistency``), chosen with the rest of the output stage on frames of the
training scenes (:func:`deltar.evaluation.zone_consistency_fit.fit_zone_consistency`): 0
leaves the depth as the network made it.
A zone whose footprint holds too little of its target (:data:`MIN_TARGET_FRACTION`: the
target is a surface the network puts elsewhere) gives no ratio. On the ten-scene
protocol the step lowered clean REL on 8-9 of the ten rooms left out
(benchmarks/RESULTS.md).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from deltar.contract import check_strength

__all__ = ["STRENGTH_CANDIDATES", "resolve_zone_consistency", "zone_consistency_field",
           "zone_consistent_depth"]

#: A footprint cell counts as on the zone's target within this many of its sigmas ...
WINDOW_SIGMAS = 3.0
#: ... or within this fraction of its reading, whichever is wider.
WINDOW_RELATIVE = 0.05
#: A zone gives a ratio only when at least this fraction of its footprint is on target.
MIN_TARGET_FRACTION = 0.25
#: Strengths ``deltar fit-uncertainty`` tries (``fit_zone_consistency``), none first.
STRENGTH_CANDIDATES: tuple[float, ...] = (0.0, 0.5, 1.0)


def resolve_zone_consistency(strength: float | None, contract: Mapping[str, Any]) -> float:
    """The strength an estimator uses (its ``zone_consistency`` argument) given the
    weights' contract: None takes the contract's (0 when it has none).

    Raises:
        ValueError: a strength outside [0, 1], given or stored.
    """
    return check_strength(contract.get("zone_consistency", 0.0) if strength is None
                          else strength)


@dataclass(frozen=True)
class _Layout:
    """What a zone layout and grid shape fix, kept between frames (a rig's zones fall on
    the same cells every frame): each footprint cell's flat index and zone, and the
    remap coordinates that spread the zones' values over the grid."""

    cells: np.ndarray   # (N,) flat indices of the cells inside some zone
    zones: np.ndarray   # (N,) their zone
    counts: np.ndarray  # (Z,) cells per zone
    map_x: np.ndarray   # (h, w) float32 zone-column coordinate of each cell
    map_y: np.ndarray   # (h, w) float32 zone-row coordinate


@functools.lru_cache(maxsize=8)
def _layout(rect_bytes: bytes, count: int, shape: tuple[int, int]) -> _Layout:
    height, width = shape
    rects = np.frombuffer(rect_bytes, dtype=np.float64).reshape(count, 4)
    grid = math.isqrt(count)
    # A cell belongs to the zone whose rectangle holds its centre (cell centres at
    # integer coordinates, as scale_rects maps them); where rectangles overlap, the later.
    labels = np.full(shape, -1, dtype=np.int64)
    bounds = np.ceil(rects)
    bounds[:, [0, 2]] = np.clip(bounds[:, [0, 2]], 0, height)
    bounds[:, [1, 3]] = np.clip(bounds[:, [1, 3]], 0, width)
    for zone, (y0, x0, y1, x1) in enumerate(bounds.astype(np.int64)):
        labels[y0:y1, x0:x1] = zone
    cells = np.flatnonzero(labels.reshape(-1) >= 0)
    zones = labels.reshape(-1)[cells]
    # Bilinear between zone centres (the mean centre of each zone row and column), the
    # nearest zones' value beyond them.
    centres_y = ((rects[:, 0] + rects[:, 2]) / 2).reshape(grid, grid).mean(axis=1)
    centres_x = ((rects[:, 1] + rects[:, 3]) / 2).reshape(grid, grid).mean(axis=0)
    rows = np.interp(np.arange(height), centres_y, np.arange(grid)).astype(np.float32)
    cols = np.interp(np.arange(width), centres_x, np.arange(grid)).astype(np.float32)
    map_x, map_y = np.meshgrid(cols, rows)
    layout = _Layout(cells, zones, np.bincount(zones, minlength=count), map_x, map_y)
    for array in (layout.cells, layout.zones, layout.counts, layout.map_x, layout.map_y):
        array.setflags(write=False)
    return layout


def zone_consistency_field(depth_m: np.ndarray, zone_rects: np.ndarray,
                           zone_mean_m: np.ndarray, zone_sigma_m: np.ndarray,
                           zone_valid: np.ndarray) -> np.ndarray | None:
    """The log correction that makes ``depth_m`` reproduce the zones' readings.

    Args:
        depth_m: (h, w) the network's depth, metres.
        zone_rects: (n * n, 4) (y0, x0, y1, x1) zone rectangles in pixels of ``depth_m``,
            row-major over the square zone grid.
        zone_mean_m, zone_sigma_m: (n, n) or (n * n,) each zone's reading and sigma, metres.
        zone_valid: (n, n) or (n * n,) bool, the zones to use (screened, on the image).

    Returns:
        (h, w) float32 log ratios (natural log of reading over depth), or None when no
        zone gives one.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    mean = np.asarray(zone_mean_m, dtype=np.float64).reshape(-1)
    sigma = np.asarray(zone_sigma_m, dtype=np.float64).reshape(-1)
    valid = np.asarray(zone_valid, dtype=bool).reshape(-1) & np.isfinite(mean) & (mean > 0)
    count = mean.size
    grid = math.isqrt(count)
    rects = np.ascontiguousarray(zone_rects, dtype=np.float64)
    if grid * grid != count or rects.shape != (count, 4) or sigma.size != count or \
            depth.ndim != 2:
        raise ValueError(f"depth_m must be (h, w), zone_rects (n * n, 4) and the readings "
                         f"(n * n,) alike, got {depth.shape}, {rects.shape}, {mean.shape}, "
                         f"{sigma.shape}")
    layout = _layout(rects.tobytes(), count, depth.shape)
    zones = layout.zones
    values = depth.reshape(-1)[layout.cells].astype(np.float64)
    window = np.maximum(WINDOW_SIGMAS * np.nan_to_num(sigma), WINDOW_RELATIVE * mean)
    on_target = valid[zones] & (np.abs(values - mean[zones]) < window[zones])
    hits = np.bincount(zones[on_target], minlength=count)
    sums = np.bincount(zones[on_target], weights=values[on_target], minlength=count)
    usable = valid & (hits > 0) & (hits >= MIN_TARGET_FRACTION * layout.counts)
    if not usable.any():
        return None
    ratios = np.zeros(count)
    ratios[usable] = np.log(mean[usable] * hits[usable] / sums[usable])
    # A zone without a ratio takes the mean of its neighbours' (0 where none has one).
    known = usable.reshape(grid, grid).astype(np.float64)
    field = ratios.reshape(grid, grid)
    total = cv2.boxFilter(field * known, -1, (3, 3), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    weight = cv2.boxFilter(known, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    field = np.where(known > 0, field, np.where(weight > 0, total / np.maximum(weight, 1), 0.0))
    return cv2.remap(field.astype(np.float32), layout.map_x, layout.map_y, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def zone_consistent_depth(depth_m: np.ndarray, zone_rects: np.ndarray,
                          zone_mean_m: np.ndarray, zone_sigma_m: np.ndarray,
                          zone_valid: np.ndarray, strength: float) -> np.ndarray:
    """``depth_m * exp(strength * zone_consistency_field(...))``: (h, w) float32 metres
    (arguments as :func:`zone_consistency_field`'s; ``strength`` in [0, 1]). The depth
    as it is when ``strength`` is 0 or no zone gives a ratio."""
    depth = np.asarray(depth_m, dtype=np.float32)
    if check_strength(strength) == 0.0:
        return depth
    field = zone_consistency_field(depth, zone_rects, zone_mean_m, zone_sigma_m, zone_valid)
    if field is None:
        return depth
    field *= np.float32(strength)
    return depth * np.exp(field)
