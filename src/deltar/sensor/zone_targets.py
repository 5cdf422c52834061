"""Several targets per zone in a zone frame: the conversion and checks of the target
arrays (:func:`convert_target_fields`, :func:`check_target_fields`) and the reading of
the drivers' flat multi-target lists (:func:`driver_readings`), for
:class:`~deltar.sensor.zone_frame.ZoneFrame`."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from deltar.sensor.zone_values import (
    DEFAULT_VALID_STATUS,
    MAX_TARGETS_PER_ZONE,
    NO_TARGET_STATUS,
    SUPPORTED_GRIDS,
    TARGET_ORDERS,
    checked_range_m,
    flags,
    grid_from_count,
    number_array,
    numbers,
    range_name,
    status_codes,
    valid_status_codes,
)


def convert_target_fields(frame: Any) -> None:
    """Convert a zone frame's target arrays in place: float32 / bool / uint8, (Z, T) flat
    input as (n, n, T), 0 in targets that are not valid.

    Args:
        frame: the :class:`~deltar.sensor.zone_frame.ZoneFrame` being built.

    Raises:
        ValueError: naming the field (a partial set, non-numbers, bad codes).
    """
    given = [name for name in ("target_mean_m", "target_sigma_m", "target_valid")
             if getattr(frame, name) is not None]
    if given and len(given) < 3:
        raise ValueError("ZoneFrame.target_mean_m, target_sigma_m and target_valid must "
                         f"be given together, got only {given}")
    if not given:
        for name in ("target_status", "target_signal"):
            if getattr(frame, name) is not None:
                raise ValueError(f"ZoneFrame.{name} needs target_mean_m, "
                                 "target_sigma_m and target_valid")
        return
    frame.target_mean_m = numbers(frame.target_mean_m,
                                  "ZoneFrame.target_mean_m").astype(np.float32)
    frame.target_sigma_m = numbers(frame.target_sigma_m,
                                   "ZoneFrame.target_sigma_m").astype(np.float32)
    frame.target_valid = flags(frame.target_valid, "ZoneFrame.target_valid")
    if frame.target_status is not None:
        frame.target_status = status_codes(frame.target_status, "ZoneFrame.target_status")
    if frame.target_signal is not None:
        frame.target_signal = numbers(frame.target_signal,
                                      "ZoneFrame.target_signal").astype(np.float32)
    n = frame.mean_m.shape[0] if frame.mean_m.ndim == 2 else -1
    for name in ("target_mean_m", "target_sigma_m", "target_valid", "target_status",
                 "target_signal"):
        arr = getattr(frame, name)
        if arr is not None and arr.ndim == 2 and n > 0 and arr.shape[0] == n * n:
            setattr(frame, name, arr.reshape(n, n, arr.shape[1]))
    # Targets that are not valid carry 0, as invalid zones do in files.
    if frame.target_valid.shape == frame.target_mean_m.shape:
        frame.target_mean_m = np.where(frame.target_valid, frame.target_mean_m,
                                      np.float32(0.0))
    if frame.target_valid.shape == frame.target_sigma_m.shape:
        frame.target_sigma_m = np.where(frame.target_valid, frame.target_sigma_m,
                                       np.float32(0.0))
    if frame.target_signal is not None and \
            frame.target_valid.shape == frame.target_signal.shape:
        frame.target_signal = np.where(frame.target_valid, frame.target_signal,
                                       np.float32(0.0))

def check_target_fields(frame: Any, n: int) -> None:
    """The checks of a zone frame's target arrays (see the ZoneFrame doc).

    Args:
        frame: the zone frame, its target arrays converted (:func:`convert_target_fields`).
        n: zones per side.

    Raises:
        ValueError: naming the field.
    """
    if frame.target_order not in TARGET_ORDERS:
        raise ValueError(f"ZoneFrame.target_order must be one of {TARGET_ORDERS}, got "
                         f"{frame.target_order!r}")
    if frame.target_mean_m is None:
        return
    mean = frame.target_mean_m
    if mean.ndim != 3 or mean.shape[:2] != (n, n) or \
            not 1 <= mean.shape[2] <= MAX_TARGETS_PER_ZONE:
        raise ValueError(f"ZoneFrame.target_mean_m must have shape ({n}, {n}, T) with "
                         f"T in 1..{MAX_TARGETS_PER_ZONE}, got {mean.shape}")
    for name in ("target_sigma_m", "target_valid", "target_status", "target_signal"):
        arr = getattr(frame, name)
        if arr is not None and arr.shape != mean.shape:
            raise ValueError(f"ZoneFrame.{name} must have shape {mean.shape} like "
                             f"target_mean_m, got {arr.shape}")
    valid = frame.target_valid
    sigma = frame.target_sigma_m
    if not np.all(np.isfinite(mean[valid])) or np.any(mean[valid] < 0):
        raise ValueError("ZoneFrame.target_mean_m must be finite and >= 0 in valid "
                         "targets, bad (row, column, target) "
                         f"{np.argwhere(valid & ~(mean >= 0)).tolist()[:5]}")
    if not np.all(np.isfinite(sigma[valid])) or np.any(sigma[valid] < 0):
        raise ValueError("ZoneFrame.target_sigma_m must be finite and >= 0 in valid "
                         "targets, bad (row, column, target) "
                         f"{np.argwhere(valid & ~(sigma >= 0)).tolist()[:5]}")
    signal = frame.target_signal
    if signal is not None and (not np.all(np.isfinite(signal[valid]))
                               or np.any(signal[valid] < 0)):
        raise ValueError("ZoneFrame.target_signal must be finite and >= 0 in valid targets")
    if frame.target_status is not None and \
            np.any(valid & (frame.target_status == NO_TARGET_STATUS)):
        raise ValueError(f"ZoneFrame.target_status is {NO_TARGET_STATUS} (no target) for "
                         "valid targets (row, column, target) "
                         f"{np.argwhere(valid & (frame.target_status == 255)).tolist()[:5]}")
    if frame.target_order == "strongest":
        # Target 0 is the primary reading: the same flags, and the same values where valid.
        differs = (valid[..., 0] != frame.valid) | (frame.valid & (
            (np.abs(mean[..., 0] - frame.mean_m) > 1e-6)
            | (np.abs(sigma[..., 0] - frame.sigma_m) > 1e-6)))
        if differs.any():
            raise ValueError("ZoneFrame.target_mean_m / target_sigma_m / target_valid "
                             "[..., 0] must equal mean_m / sigma_m / valid in "
                             "'strongest' order (target 0 is the primary reading); "
                             f"they differ at zones {np.argwhere(differs).tolist()[:5]}")


#: Driver readings whose valid distances all lie below this (metres; the sensor ranges
#: from 0.02 m) are taken for metres written as millimetres ...
MILLIMETRE_FLOOR_M = 0.01
#: ... when at least this many targets are valid.
MIN_UNIT_CHECK_TARGETS = 4


def driver_readings(
    distance_mm: Sequence[float],
    range_sigma_mm: Sequence[float],
    target_status: Sequence[int],
    *,
    grid: int | None = None,
    valid_status: Sequence[int] = DEFAULT_VALID_STATUS,
    orientation: Any = None,
    sensor_model: str = "VL53L5CX",
    nb_target_detected: Sequence[int] | None = None,
    targets_per_zone: int | None = None,
    target_order: str = "strongest",
    signal_per_spad: Sequence[float] | None = None,
) -> dict[str, Any]:
    """The zone frame fields of what the Python drivers return (for ``ZoneFrame.from_driver``).

    Driver builds for several targets per zone (``VL53L5CX_NB_TARGET_PER_ZONE`` = T)
    return ``zones * T`` entries per field, zone-major: entry ``zone * T + t`` is
    target ``t`` of ``zone``. The primary reading (``mean_m``, ``sigma_m``, ``valid``)
    is each zone's first target; with T > 1 (or ``targets_per_zone`` given) the frame
    also holds every target (``target_mean_m`` ... (n, n, T)).

    Args:
        distance_mm: flat list of ``zones * T`` distances in millimetres (driver
            order). Targets reading 0 or less (error codes) or more than the sensor
            model's range (:data:`SENSOR_MAX_RANGE_M`; for a model not listed there
            :data:`UNKNOWN_MODEL_MAX_RANGE_M`, as the physical checks hold it; with a
            ``RuntimeWarning``) are invalid.
        range_sigma_mm: flat list of the same length, sigma in millimetres.
        target_status: flat list of the same length, ST's target status codes.
        grid: 4 or 8; inferred when None: from ``nb_target_detected``'s length when
            given, else from the length of ``distance_mm`` (16 -> 4, 64 -> 8, one
            target per zone).
        valid_status: status codes that count as a valid range (default 5 and 9).
        orientation: an :class:`~deltar.sensor.zone_frame.Orientation`, how the driver's
            grid maps onto the image (identity when None).
        sensor_model: the sensor model, whose range applies (free text: a model not
            listed is held to :data:`UNKNOWN_MODEL_MAX_RANGE_M`, said in the warning).
        nb_target_detected: optional flat list of ``zones`` counts (driver order), the
            number of targets each zone detected, each in 0..4; target ``t`` of a zone
            is valid only when ``t`` is below its count (the driver leaves stale values
            beyond it).
        targets_per_zone: T, 1..4; inferred from the lengths when None (``len /
            zones``), except that a 4x4 reading of ``64 * T`` entries is ST's results
            buffer, sized for 8x8 whatever the resolution, as the Python drivers return
            it: its first ``16 * T`` entries are read (64 entries: one target per zone;
            a compact dump of 16 zones x 4 targets needs ``targets_per_zone=4``).
        target_order: ``"strongest"`` (the driver's default) or ``"closest"``, as
            the driver was configured (``vl53l5cx_set_target_order``).
        signal_per_spad: optional flat list like ``distance_mm``, each target's return
            signal (kcps per SPAD), kept as ``target_signal`` with several targets.

    Returns:
        ``ZoneFrame`` keyword arguments: ``mean_m``, ``sigma_m``, ``valid``, ``status``
        (n, n) and, with several targets, the target arrays (n, n, T) and
        ``target_order``.

    Raises:
        ValueError: a required list missing, lengths that do not fit ``grid`` and
            ``targets_per_zone``, codes (also ``valid_status``) that are not integers in
            0..255, target counts (``nb_target_detected``) above 4, an ``orientation``
            that is not one, an unknown ``target_order``,
            distances that are metres (every valid one below :data:`MILLIMETRE_FLOOR_M`),
            naming the argument.
    """
    arrays = {}
    for name, values in (("distance_mm", distance_mm), ("range_sigma_mm", range_sigma_mm),
                         ("target_status", target_status), ("signal_per_spad", signal_per_spad)):
        if values is None and name != "signal_per_spad":
            raise ValueError(f"{name} is required: the driver's list of one entry per zone "
                             "and target")
        if values is not None:
            arrays[name] = number_array(values, name)
    valid_codes = valid_status_codes(valid_status)
    if orientation is not None and not callable(getattr(orientation, "apply", None)):
        raise ValueError(f"orientation must be an Orientation (e.g. Orientation(flip_ud="
                         f"True)) or None, got {orientation!r}")
    sizes = [arr.size for arr in arrays.values()]
    if len(set(sizes)) > 1:
        *first, last = arrays
        raise ValueError(f"{', '.join(first)} and {last} must have the same length (one "
                         f"entry per zone and target), got {sizes}")
    if target_order not in TARGET_ORDERS:
        raise ValueError(f"target_order must be one of {TARGET_ORDERS}, got "
                         f"{target_order!r}")
    detected = None
    if nb_target_detected is not None:
        detected = status_codes(number_array(nb_target_detected, "nb_target_detected"),
                                "nb_target_detected").astype(np.int64)
    if targets_per_zone is not None and (
            isinstance(targets_per_zone, (bool, np.bool_))
            or not isinstance(targets_per_zone, (int, np.integer))
            or not 1 <= targets_per_zone <= MAX_TARGETS_PER_ZONE):
        raise ValueError(f"targets_per_zone must be an integer in "
                         f"1..{MAX_TARGETS_PER_ZONE}, got {targets_per_zone!r}")
    if grid is not None:
        if isinstance(grid, (bool, np.bool_)) or not isinstance(grid, (int, np.integer)):
            raise ValueError(f"grid must be one of {SUPPORTED_GRIDS}, got {grid!r}")
        n = int(grid)
    elif detected is not None:
        n = grid_from_count(detected.size, "nb_target_detected")
    elif targets_per_zone is not None and sizes[0] % targets_per_zone == 0:
        n = grid_from_count(sizes[0] // targets_per_zone, "distance_mm")
    elif sizes[0] in (16, 64):
        n = grid_from_count(sizes[0], "distance_mm")
    else:
        raise ValueError(f"distance_mm has {sizes[0]} entries; expected 16 (4x4) or 64 "
                         "(8x8), or pass grid= or targets_per_zone= for a driver that "
                         "reports several targets per zone")
    if n not in SUPPORTED_GRIDS:
        raise ValueError(f"grid must be one of {SUPPORTED_GRIDS}, got {n}")
    zones = n * n
    size = sizes[0]
    if targets_per_zone is not None:
        per_zone = int(targets_per_zone)
        # ST's buffers are sized for 8x8; in 4x4 mode the first 16 zones are filled.
        used = zones * per_zone
        if size != used and not (n == 4 and size == 64 * per_zone):
            raise ValueError(f"distance_mm has {size} entries; expected {used} for a "
                             f"{n}x{n} grid with {per_zone} target(s) per zone")
    elif n == 4 and 0 < size <= 64 * MAX_TARGETS_PER_ZONE and size % 64 == 0 and (
            detected is None or detected.size == 64):
        # ST's results buffer, sized for 8x8 whatever the resolution (64 * T entries,
        # and 64 counts in nb_target_detected), of which 4x4 mode fills the first 16 * T:
        # what the Python drivers return. A compact dump of 16 zones x 4 targets (also
        # 64 entries) says so with targets_per_zone.
        per_zone = size // 64
    else:
        if size < zones or size % zones:
            raise ValueError(f"distance_mm has {size} entries; expected {zones} for a "
                             f"{n}x{n} grid (times the targets per zone)")
        per_zone = size // zones
        if per_zone > MAX_TARGETS_PER_ZONE:
            raise ValueError(f"distance_mm has {size} entries, {per_zone} per zone of a "
                             f"{n}x{n} grid; the driver reports at most "
                             f"{MAX_TARGETS_PER_ZONE} targets per zone")
    if detected is not None:
        if detected.size == 64 and n == 4:
            detected = detected[:16]
        if detected.size != zones:
            raise ValueError(f"nb_target_detected has {detected.size} entries; expected "
                             f"{zones} (one per zone of the {n}x{n} grid)")
        many = np.flatnonzero(detected > MAX_TARGETS_PER_ZONE)
        if many.size:
            raise ValueError(f"nb_target_detected must hold target counts in "
                             f"0..{MAX_TARGETS_PER_ZONE} (the sensor reports at most "
                             f"{MAX_TARGETS_PER_ZONE} targets per zone), got "
                             f"{detected[many[0]]} for zone {many[0]} (driver order)")
    for name, arr in arrays.items():
        # Zone-major: target t of zone z at z * per_zone + t.
        arrays[name] = arr[: zones * per_zone].reshape(zones, per_zone)
    status = status_codes(arrays["target_status"], "target_status")
    valid = np.isin(status, valid_codes)
    valid &= status != NO_TARGET_STATUS
    if detected is not None:
        valid &= np.arange(per_zone)[None, :] < detected[:, None]
    mean = arrays["distance_mm"] / 1000.0
    sigma = arrays["range_sigma_mm"] / 1000.0
    valid &= np.isfinite(mean) & np.isfinite(sigma) & (mean > 0) & (sigma >= 0)
    if valid.sum() >= MIN_UNIT_CHECK_TARGETS and mean[valid].max() < MILLIMETRE_FLOOR_M:
        # The sensor ranges from 20 mm: readings that all lie below 10 "mm" are metres.
        raise ValueError(f"distance_mm must be millimetres, but every valid reading is "
                         f"below {MILLIMETRE_FLOOR_M * 1000:g} mm (up to "
                         f"{mean[valid].max() * 1000:.4g}); were metres written?")
    # Readings beyond the sensor's range are not measurements: invalid, visibly (an
    # unknown model is held to the range the physical checks hold it to, now).
    limit = checked_range_m(sensor_model)
    for far, what, values in ((valid & (mean > limit), "read more than", mean),
                              (valid & (sigma > limit), "have a sigma larger than", sigma)):
        if far.any():
            unit = "zone(s)" if per_zone == 1 else "target(s)"
            warnings.warn(f"{int(far.sum())} {unit} with a valid status {what} the "
                          f"{range_name(sensor_model)} (up to {values[far].max():.6g} m); "
                          "marked invalid", RuntimeWarning, stacklevel=2)
            valid &= ~far
    signal = arrays.get("signal_per_spad", np.zeros_like(mean))
    mean, sigma, valid, status, signal = (a.reshape(n, n, per_zone)
                                          for a in (mean, sigma, valid, status, signal))
    if orientation is not None:
        mean, sigma, valid, status, signal = (orientation.apply(a)
                                              for a in (mean, sigma, valid, status, signal))
    mean = np.where(valid, mean, 0.0).astype(np.float32)
    sigma = np.where(valid, sigma, 0.0).astype(np.float32)
    targets = {}
    if per_zone > 1 or targets_per_zone is not None:
        targets = {"target_mean_m": mean, "target_sigma_m": sigma, "target_valid": valid,
                   "target_status": status, "target_order": target_order}
        if "signal_per_spad" in arrays:
            good = valid & np.isfinite(signal) & (signal >= 0)
            targets["target_signal"] = np.where(good, signal, 0.0).astype(np.float32)
    return {"mean_m": mean[..., 0], "sigma_m": sigma[..., 0], "valid": valid[..., 0],
            "status": status[..., 0], **targets}
