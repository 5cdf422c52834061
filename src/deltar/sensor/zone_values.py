"""Values of a zone reading: the sensor constants (status codes, grids, range, targets
per zone) and the checked conversions of numbers, flags and status codes that the zone
frame (:mod:`deltar.sensor.zone_frame`) and its readers use."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Target status codes that ST documents as a valid range (5: valid, 9: valid, large pulse).
DEFAULT_VALID_STATUS: tuple[int, ...] = (5, 9)
#: ST's "no target detected": nothing returned within the sensor's range.
NO_TARGET_STATUS = 255
#: Most targets per zone ST's driver reports (``VL53L5CX_NB_TARGET_PER_ZONE``, 1 to 4).
MAX_TARGETS_PER_ZONE = 4
#: Orders the driver reports a zone's targets in: strongest return first (the default)
#: or closest first (``vl53l5cx_set_target_order``).
TARGET_ORDERS: tuple[str, ...] = ("strongest", "closest")

SUPPORTED_GRIDS: tuple[int, ...] = (4, 8)


def is_supported_grid(value: Any) -> bool:
    """Whether ``value`` is one of :data:`SUPPORTED_GRIDS` as an integer (zones per side):
    ``True`` and ``8.0`` are not (a float grid fails later, as a slice bound)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_) \
        and value in SUPPORTED_GRIDS


#: The eight neighbours of a zone, (dy, dx) row by row.
NEIGHBOURS_3x3: tuple[tuple[int, int], ...] = tuple(
    (dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)

#: Largest distance each sensor model reports, metres (ST datasheets: "up to 4 m").
#: A valid zone must read ``0 < d <= range``; the physical checks hold unknown models
#: to :data:`UNKNOWN_MODEL_MAX_RANGE_M`.
SENSOR_MAX_RANGE_M: dict[str, float] = {"VL53L5CX": 4.0, "VL53L8CX": 4.0}

#: The range the physical checks hold a frame of an unknown sensor model to, metres: no
#: multi-zone ToF sensor reads this far (its list: SENSOR_MAX_RANGE_M).
UNKNOWN_MODEL_MAX_RANGE_M = 20.0


def sensor_max_range_m(sensor_model: str) -> float:
    """The largest distance ``sensor_model`` reports, metres (``inf`` when unknown)."""
    return SENSOR_MAX_RANGE_M.get(str(sensor_model).upper(), math.inf)


def checked_range_m(sensor_model: str, max_range_m: float | None = None) -> float:
    """The range a reading of ``sensor_model`` is held to, metres: ``max_range_m`` when
    given, else the model's (:data:`SENSOR_MAX_RANGE_M`); where that is infinite (a model
    not listed: a typo, or a sensor deltar does not know)
    :data:`UNKNOWN_MODEL_MAX_RANGE_M`, which no multi-zone ToF sensor reaches (millimetres
    written as metres exceed it)."""
    limit = sensor_max_range_m(sensor_model) if max_range_m is None else max_range_m
    return limit if math.isfinite(limit) else UNKNOWN_MODEL_MAX_RANGE_M


def range_name(sensor_model: str) -> str:
    """How messages name the range :func:`checked_range_m` holds ``sensor_model`` to:
    ``"VL53L5CX's 4 m range"``, or for an unknown model ``"20 m range held for the
    unknown sensor model 'X' (known: VL53L5CX, VL53L8CX)"``."""
    if math.isfinite(sensor_max_range_m(sensor_model)):
        return f"{sensor_model}'s {checked_range_m(sensor_model):g} m range"
    return (f"{UNKNOWN_MODEL_MAX_RANGE_M:g} m range held for the unknown sensor model "
            f"{sensor_model!r} (known: {', '.join(SENSOR_MAX_RANGE_M)})")


def number_array(values, name: str) -> np.ndarray:
    """Flat float64 array of a list (or array) of numbers, refusing anything else.

    Strings (``"1.5"``) and booleans are refused rather than converted: a file or driver
    that stores them is not what the reader expects, and converting hides that.

    Args:
        values: a (nested) list or tuple of int / float, or a numeric numpy array.
        name: what the values are, for the error message (e.g. ``"zones.json: mean_m"``).

    Raises:
        ValueError: ``"<name> must hold numbers, got ..."``, or nested lists that are
            not rows of one length.
    """
    if isinstance(values, np.ndarray):
        if values.dtype.kind not in "iuf":
            raise ValueError(f"{name} must hold numbers, got an array of {values.dtype}")
        return values.astype(np.float64).reshape(-1)
    if not isinstance(values, (list, tuple)):
        raise ValueError(f"{name} must be a list of numbers, got {type(values).__name__}")
    flat: list = []
    pending = [values]
    while pending:
        item = pending.pop()
        if isinstance(item, (list, tuple)):
            pending.extend(reversed(item))
        else:
            flat.append(item)
    bad = [v for v in flat if isinstance(v, (bool, np.bool_))
           or not isinstance(v, (int, float, np.integer, np.floating))]
    if bad:
        raise ValueError(f"{name} must hold numbers, got {type(bad[0]).__name__} "
                         f"{bad[0]!r}" + (f" and {len(bad) - 1} more" if len(bad) > 1 else ""))
    try:  # nested lists must be rows of one length (a grid), not a ragged mix
        return np.asarray(values, dtype=np.float64).reshape(-1)
    except ValueError:
        raise ValueError(f"{name} must be a flat list of numbers or rows of equal length, "
                         "got nested lists of different lengths") from None


def valid_status_codes(values: Any, name: str = "valid_status") -> np.ndarray:
    """The status codes that count as valid: one integer or any iterable of them (a
    list, tuple, set, range or array), as uint8, refusing what is not a code 0..255."""
    if isinstance(values, int | np.integer) and not isinstance(values, bool):
        values = [values]
    elif not isinstance(values, str | bytes | np.ndarray | list | tuple) and hasattr(
            values, "__iter__"):
        values = list(values)
    return status_codes(number_array(values, name), name)


def status_codes(values, name: str) -> np.ndarray:
    """ST target status codes as uint8, refusing what is not an integer in 0..255.

    Fractional codes (``5.5``), codes out of range and non-numbers are refused rather
    than truncated or wrapped.

    Args:
        values: array-like of codes.
        name: what the codes are, for the message.

    Raises:
        ValueError: ``"<name> must hold integer codes in 0..255, got <value>"``.
    """
    codes = numbers(values, name)
    bad = ~np.isfinite(codes) | (codes < 0) | (codes > 255) | (codes != np.round(codes))
    if np.any(bad):
        raise ValueError(f"{name} must hold integer codes in 0..255, got "
                         f"{codes[bad].reshape(-1)[0]:g}")
    return codes.astype(np.uint8)


def numbers(values, name: str) -> np.ndarray:
    """An array of numbers (any shape), refusing strings, booleans and objects."""
    array = np.asarray(values)
    if array.dtype.kind not in "iuf":
        shown = "booleans" if array.dtype.kind == "b" else f"values of type {array.dtype}"
        raise ValueError(f"{name} must hold numbers, got {shown}")
    return array


def flags(values, name: str) -> np.ndarray:
    """A bool array of booleans or 0/1 numbers, refusing strings and other numbers."""
    array = np.asarray(values)
    if array.dtype.kind != "b" and (array.dtype.kind not in "iuf"
                                    or not np.all(np.isin(array, (0, 1)))):
        raise ValueError(f"{name} must hold booleans (or 0/1), got values of type "
                         f"{array.dtype}" + ("" if array.dtype.kind not in "iuf" else
                                             " other than 0 and 1"))
    return array.astype(bool)


def grid_from_count(count: int, name: str) -> int:
    """Zones per side (4 or 8) of ``count`` zones; ``ValueError`` naming ``name``
    for any other count."""
    n = math.isqrt(count)
    if n * n != count or n not in SUPPORTED_GRIDS:
        raise ValueError(f"{name} has {count} zones; expected 16 (4x4) or 64 (8x8)")
    return n


def zone_neighbours(values: np.ndarray, offsets: tuple[tuple[int, int], ...] = NEIGHBOURS_3x3,
                    fill: float = np.nan) -> np.ndarray:
    """Each zone's neighbours' values.

    Args:
        values: (n, n) one value per zone.
        offsets: (dy, dx) of the neighbours, each within 2 zones.
        fill: the value of a neighbour off the grid.

    Returns:
        (len(offsets), n, n), the dtype of ``values`` and ``fill`` together (float32
        readings stay float32): entry [k, y, x] is ``values[y + dy_k, x + dx_k]``,
        ``fill`` off the grid.
    """
    n = values.shape[0]
    padded = np.full((n + 4, n + 4), fill, dtype=np.result_type(values, fill))
    padded[2:-2, 2:-2] = values
    windows = np.lib.stride_tricks.sliding_window_view(padded, (5, 5))  # (n, n, 5, 5)
    rows, cols = zip(*((2 + dy, 2 + dx) for dy, dx in offsets), strict=True)
    return np.moveaxis(windows[:, :, list(rows), list(cols)], -1, 0)
