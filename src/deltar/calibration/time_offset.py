"""The clock offset between the sensor's and the camera's streams, from the board.

The camera sees the board's plane at a distance that changes as the rig moves, and the
zones see the same plane; once the clocks agree the two distances differ by a constant
(or by ``n_c . t`` for the unknown sensor position t). The offset that makes them agree
best is the estimate (``deltar calibrate --time-offset auto``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """A time offset between the streams estimated from the board's distance.

    Attributes:
        offset_s: how far the camera's stamps run ahead of the sensor's, seconds.
        residual_m: RMS of zone distance - camera distance (bias removed, worst 10 % left
            out) at the offset, metres.
        residual_at_zero_m: the same with no offset.
        samples: zone frames compared at the offset.
    """

    offset_s: float
    residual_m: float
    residual_at_zero_m: float
    samples: int



def estimate_time_offset(image_times_s: np.ndarray, camera_distance_m: np.ndarray,
                         zone_times_s: np.ndarray, zone_distance_m: np.ndarray, *,
                         camera_normals: np.ndarray | None = None,
                         max_offset_s: float = 0.5, step_s: float = 0.002,
                         min_motion_m: float = 0.03) -> TimeOffsetEstimate:
    """The camera-minus-sensor clock offset that best lines up the two distance series.

    The camera sees the board's plane at ``camera_distance_m`` over time and the zones
    see the same plane at ``zone_distance_m``. Once the clocks agree the two differ by a
    constant, or, with ``camera_normals``, by ``n_c . t`` for the unknown sensor
    position t (plane offsets: ``d_s = d_c + n_c . t``), fitted per candidate. Every
    candidate offset on a ``step_s`` grid in ``[-max_offset_s, max_offset_s]`` is scored
    by the RMS of the differences about their median (the worst 10 % left out) over
    zone frames whose shifted time falls between two board detections, and the best is refined by a
    parabola through its neighbours.

    Args:
        image_times_s: (N,) increasing image stamps with the board found, seconds.
        camera_distance_m: (N,) camera-to-plane distances, metres.
        camera_normals: optional (N, 3) the plane's unit normals in the camera frame.
        zone_times_s: (M,) zone frame stamps, seconds.
        zone_distance_m: (M,) sensor-to-plane distances, metres.
        max_offset_s: largest offset searched, seconds.
        step_s: search step, seconds.
        min_motion_m: the camera distance must vary at least this much (std, metres).

    Raises:
        ValueError: too few samples, or the distance does not change enough to time it
            (the message says to move the rig or to pass the offset).
    """
    ti = np.asarray(image_times_s, dtype=np.float64)
    di = np.asarray(camera_distance_m, dtype=np.float64)
    tz = np.asarray(zone_times_s, dtype=np.float64)
    dz = np.asarray(zone_distance_m, dtype=np.float64)
    if ti.size < 10 or tz.size < 10:
        raise ValueError(f"--time-offset auto needs the board in at least 10 images and 10 "
                         f"zone frames with a plane, got {ti.size} and {tz.size}: pass "
                         "--time-offset SECONDS instead")
    if np.std(di) < min_motion_m:
        raise ValueError(f"--time-offset auto: the board's distance hardly changes (std "
                         f"{100 * np.std(di):.1f} cm, need {100 * min_motion_m:.0f} cm): move "
                         "the rig towards and away from the board while recording, or pass "
                         "--time-offset SECONDS")
    gaps = np.diff(ti)
    max_gap = 3.0 * float(np.median(gaps))
    candidates = np.arange(-max_offset_s, max_offset_s + step_s / 2, step_s)
    costs = np.full(candidates.size, np.inf)
    counts = np.zeros(candidates.size, dtype=np.int64)
    for k, offset in enumerate(candidates):
        shifted = tz + offset
        right = np.searchsorted(ti, shifted)
        inside = (right > 0) & (right < ti.size)
        right_c = np.clip(right, 1, ti.size - 1)
        inside &= (ti[right_c] - ti[right_c - 1]) <= max_gap
        if inside.sum() < 10:
            continue
        diff = dz[inside] - np.interp(shifted[inside], ti, di)
        if camera_normals is not None:
            normals = np.column_stack([np.interp(shifted[inside], ti, camera_normals[:, j])
                                       for j in range(3)])
            diff = diff - normals @ np.linalg.lstsq(normals, diff, rcond=None)[0]
        # RMS of the differences about their median, the worst 10 % left out (a few
        # zone planes from another surface must not decide the offset).
        spread = np.sort(np.abs(diff - np.median(diff)))[:max(1, int(0.9 * diff.size))]
        costs[k] = float(np.sqrt(np.mean(spread ** 2)))
        counts[k] = int(inside.sum())
    enough = counts >= 0.5 * counts.max()
    costs[~enough] = np.inf
    if not np.isfinite(costs).any():
        raise ValueError("--time-offset auto: the zone frames and the board images do not "
                         "overlap in time: pass --time-offset SECONDS")
    best = int(np.argmin(costs))
    offset = float(candidates[best])
    if 0 < best < candidates.size - 1 and np.all(np.isfinite(costs[best - 1:best + 2])):
        c0, c1, c2 = costs[best - 1:best + 2]
        curve = c0 - 2 * c1 + c2
        if curve > 0:
            offset += float(np.clip(0.5 * (c0 - c2) / curve, -1, 1)) * step_s
    zero = int(np.argmin(np.abs(candidates)))
    return TimeOffsetEstimate(offset, float(costs[best]), float(costs[zero]), int(counts[best]))
