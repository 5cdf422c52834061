"""Zones that reported no target, for readings that do not say which ones did.

A VL53L5CX / L8CX zone that returns nothing within its range (ST status 255) tells the
network that its surface is farther than about 4 m; the plane-select head and the
confidence blend read such a zone at ``no_target_depth``. Some readings carry only a
validity mask: the released ZJU-L5 files, drivers that keep valid zones alone. There an
invalid zone is either beyond the range or a failed reading (low signal, inconsistent
pulses), and reading every invalid zone as far would push failed zones among near
surfaces to 5 m. The rule here reads an invalid zone as *no target* only when a valid
neighbour (of the eight around it) already reads at least ``min_neighbour_m``, or when
none of its neighbours is valid: a zone that returned nothing next to one that sees far
is most likely looking past the range. A frame without any valid zone gets no flag: with
nothing returned anywhere, a blocked or failed sensor cannot be told from an empty
view, and the estimate stays image-only. The threshold is fitted with the output stage on
frames of the training scenes with their flags removed
(:func:`deltar.evaluation.uncertainty.fit_no_target_inference`).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_values import zone_neighbours

__all__ = ["check_min_neighbour_m", "frame_no_target", "infer_no_target"]


def infer_no_target(zone_mean_m: np.ndarray, zone_valid: np.ndarray,
                    min_neighbour_m: float) -> np.ndarray:
    """Invalid zones read as *no target* by the neighbour rule (module docstring).

    Args:
        zone_mean_m: (n, n) zone readings in metres (ignored where not valid).
        zone_valid: (n, n) bool validity.
        min_neighbour_m: metres; an invalid zone is read as no target when one of its
            eight neighbours is valid and reads at least this much, or none is valid
            (while some zone of the frame is).

    Returns:
        (n, n) bool, True at the invalid zones read as no target (never at valid ones;
        none when no zone is valid).

    Raises:
        ValueError: shapes differ or are not square, or ``min_neighbour_m`` is not a
            finite number >= 0.
    """
    valid = np.asarray(zone_valid, dtype=bool)
    mean = np.asarray(zone_mean_m, dtype=np.float64)
    if valid.ndim != 2 or valid.shape[0] != valid.shape[1] or mean.shape != valid.shape:
        raise ValueError(f"zone_mean_m and zone_valid must both be (n, n), got "
                         f"{mean.shape} and {valid.shape}")
    if check_min_neighbour_m(min_neighbour_m) is None:
        raise ValueError("min_neighbour_m must be a finite number of metres >= 0, got None")
    if not valid.any():
        return np.zeros_like(valid)
    # Invalid zones and the border read -inf, so they never count as a far neighbour.
    farthest = zone_neighbours(np.where(valid, mean, -np.inf), fill=-np.inf).max(axis=0)
    return ~valid & ((farthest >= min_neighbour_m) | np.isneginf(farthest))


def check_min_neighbour_m(value: object, name: str = "min_neighbour_m") -> float | None:
    """The rule's threshold as float metres, or None (no inference).

    Args:
        value: metres (any real number, numpy scalars too) or None.
        name: the argument's name in the error message.

    Raises:
        ValueError: neither None nor a finite number >= 0 (the message names ``name``).
    """
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or \
            not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a finite number of metres >= 0 or None, got "
                         f"{value!r}")
    return float(value)


def frame_no_target(frame: ZoneFrame, min_neighbour_m: float | None) -> np.ndarray:
    """(Z,) bool row-major no-target flags of a frame, inferred when it carries none.

    Args:
        frame: the zone frame.
        min_neighbour_m: metres, the rule's threshold (:func:`infer_no_target`) for a
            frame without flags (``frame.no_target is None``); None: such a frame has
            no zone read as no target.

    Returns:
        The frame's own flags when it has them (also when none is set), else the
        inferred ones, else all False.
    """
    if frame.no_target is not None or min_neighbour_m is None:
        return frame.flat_no_target()
    return infer_no_target(frame.mean_m, frame.valid, min_neighbour_m).reshape(-1)
