"""Zone-frame files: one ToF reading as JSON or NPZ, and raw driver dumps.

JSON layout (``schema_version`` 1), flat row-major lists of ``zone_count`` entries::

    {"schema": "deltar.zone_frame", "schema_version": 1, "sensor_model": "VL53L5CX",
     "zone_count": 64, "timestamp_s": 12.5,
     "mean_m": [...], "sigma_m": [...], "valid": [...],
     "status": [...],                        # optional, uint8 target status codes
     "no_target": [...],                     # optional, bools: zones with no target
     "hist_edges_m": [...], "hist_counts": [[...], ...],   # optional, (B + 1,), (Z, B)
     "targets_per_zone": 2, "target_order": "strongest",   # optional: every target
     "target_mean_m": [[...], ...], "target_sigma_m": [[...], ...],   # (Z, T) metres
     "target_valid": [[...], ...], "target_status": [[...], ...],     # (Z, T), status optional
     "target_signal": [[...], ...]}          # optional (Z, T) >= 0, each target's return signal

The target keys are written only for frames that hold several targets per zone
(``ZoneFrame.target_mean_m``); a single-target frame's file is as before, and readers
that do not know the keys ignore them.

NPZ files hold the same keys as arrays (``schema``/``sensor_model`` as 0-d strings).
A raw driver dump is a JSON object with ``distance_mm``, ``range_sigma_mm`` and
``target_status`` (flat lists of 16 or 64, driver order), as the Python drivers return;
multi-target builds return ``zones * T`` entries (zone-major), optionally with
``nb_target_detected`` (one per zone), ``signal_per_spad`` (like ``distance_mm``),
``targets_per_zone`` and ``target_order``.

Values must be numbers: strings (``"1.5"``) and booleans (``true``) are refused, not
converted. A schema file's valid zones must read a distance the sensor can measure
(``0 < d <= 4 m`` for the VL53L5CX/L8CX, see
:data:`~deltar.sensor.zone_values.SENSOR_MAX_RANGE_M`); a driver dump's zones outside
that range are marked invalid with a warning, as error codes (``d <= 0``) always are.
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from deltar.io.atomic import atomic_path, write_text_atomic
from deltar.io.input_file import input_file, reading
from deltar.io.json_file import read_json
from deltar.sensor.zone_frame import Orientation, ZoneFrame
from deltar.sensor.zone_values import DEFAULT_VALID_STATUS, is_supported_grid, number_array

SCHEMA_NAME = "deltar.zone_frame"
SCHEMA_VERSION = 1
_DRIVER_FIELDS = ("distance_mm", "range_sigma_mm", "target_status")
_TARGET_KEYS = ("target_mean_m", "target_sigma_m", "target_valid", "target_status",
                "target_signal")


def check_writable(frame: Any) -> ZoneFrame:
    """Refuse to write what no reader would read back: not a ``ZoneFrame``, fields
    reassigned inconsistently since it was made, or a reading no sensor can give (e.g.
    millimetres as metres; :meth:`ZoneFrame.physical_error`). A recording holding such a
    frame could not be read at all.

    Raises:
        ValueError: naming what is wrong.
    """
    if not isinstance(frame, ZoneFrame):
        raise ValueError(f"frame must be a ZoneFrame, got {type(frame).__name__}")
    frame.validate()
    problem = frame.physical_error()
    if problem is not None:
        raise ValueError(f"refusing to write a zone frame its reader would refuse: {problem}")
    return frame


def zone_frame_to_dict(frame: ZoneFrame) -> dict[str, Any]:
    """The JSON-ready dict of ``frame`` (flat row-major lists; metres; see module doc).
    The writers check the frame first (:func:`check_writable`)."""
    mean, sigma, valid = frame.flat()
    data: dict[str, Any] = {
        "schema": SCHEMA_NAME,
        "schema_version": SCHEMA_VERSION,
        "sensor_model": frame.sensor_model,
        "zone_count": frame.zone_count,
        "timestamp_s": None if frame.timestamp_s is None else float(frame.timestamp_s),
        # Invalid zones carry 0.0 by convention, never a stale distance.
        "mean_m": np.where(valid, mean, 0.0).astype(float).tolist(),
        "sigma_m": np.where(valid, sigma, 0.0).astype(float).tolist(),
        "valid": valid.tolist(),
    }
    if frame.status is not None:
        data["status"] = frame.status.reshape(-1).astype(int).tolist()
    if frame.no_target is not None:
        data["no_target"] = frame.flat_no_target().tolist()
    if frame.hist_counts is not None:
        data["hist_edges_m"] = frame.hist_edges_m.astype(float).tolist()
        data["hist_counts"] = frame.hist_counts.reshape(frame.zone_count, -1).astype(
            float).tolist()
    if frame.target_mean_m is not None:
        mean, sigma, valid = frame.flat_targets()
        data["targets_per_zone"] = frame.targets_per_zone
        data["target_order"] = frame.target_order
        data["target_mean_m"] = mean.astype(float).tolist()
        data["target_sigma_m"] = sigma.astype(float).tolist()
        data["target_valid"] = valid.tolist()
        if frame.target_status is not None:
            data["target_status"] = frame.target_status.reshape(frame.zone_count, -1).astype(
                int).tolist()
        if frame.target_signal is not None:
            data["target_signal"] = frame.target_signal.reshape(frame.zone_count, -1).astype(
                float).tolist()
    return data


def zone_frame_from_dict(data: Mapping[str, Any], *, source: str = "zone frame",
                         orientation: Orientation | None = None,
                         valid_status: tuple[int, ...] = DEFAULT_VALID_STATUS) -> ZoneFrame:
    """Build a ``ZoneFrame`` from a schema dict or a raw driver dict.

    Args:
        data: either this module's schema (``mean_m`` ...) or a driver dict with
            ``distance_mm``, ``range_sigma_mm``, ``target_status`` (flat lists, millimetres).
        source: name used in error messages (e.g. the file path).
        orientation: for driver dicts only, how the driver grid maps onto the image.
        valid_status: for driver dicts only, status codes counted as valid.

    Raises:
        ValueError: naming ``source`` and the problem (missing keys, wrong zone count,
            NaN or negative values, unknown schema version).
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"{source}: expected a JSON object, got {type(data).__name__}")
    sensor_model = data.get("sensor_model", "VL53L5CX")
    if not isinstance(sensor_model, str):
        raise ValueError(f"{source}: sensor_model must be a string, got {sensor_model!r}")
    present = [k for k in _DRIVER_FIELDS if k in data]
    if present and len(present) < len(_DRIVER_FIELDS) and "schema_version" not in data:
        missing = [k for k in _DRIVER_FIELDS if k not in data]
        raise ValueError(f"{source}: a raw driver dump needs {', '.join(_DRIVER_FIELDS)}; "
                         f"{', '.join(missing)} missing")
    if all(k in data for k in _DRIVER_FIELDS):
        fields = [number_array(data[k], f"{source}: {k}") for k in _DRIVER_FIELDS]
        grid = data.get("grid")
        if grid is not None and not is_supported_grid(grid):
            raise ValueError(f"{source}: grid must be 4 or 8 (the driver's resolution), got "
                             f"{grid!r}")
        detected, signal = data.get("nb_target_detected"), data.get("signal_per_spad")
        if detected is not None:
            detected = number_array(detected, f"{source}: nb_target_detected")
        if signal is not None:
            signal = number_array(signal, f"{source}: signal_per_spad")
        per_zone = data.get("targets_per_zone")
        if isinstance(per_zone, np.integer):
            per_zone = int(per_zone)
        timestamp = _optional_float(data.get("timestamp_s"), source, "timestamp_s")
        try:
            return ZoneFrame.from_driver(
                *fields, orientation=orientation, valid_status=valid_status,
                timestamp_s=timestamp,
                sensor_model=sensor_model, nb_target_detected=detected, grid=grid,
                targets_per_zone=per_zone, signal_per_spad=signal,
                target_order=data.get("target_order", "strongest"))
        except (TypeError, ValueError) as err:
            raise ValueError(f"{source}: invalid driver output: {err}") from err
    if orientation is not None and orientation != Orientation():
        # Silently ignoring it would leave the user believing the grid was turned.
        raise ValueError(f"{source}: a zone file in deltar's schema is already in image "
                         "orientation; a driver orientation applies to raw driver dumps "
                         f"({', '.join(_DRIVER_FIELDS)}) only")
    if data.get("schema", SCHEMA_NAME) != SCHEMA_NAME:
        raise ValueError(f"{source}: schema is {data.get('schema')!r}, expected {SCHEMA_NAME!r}")
    version = data.get("schema_version")
    if isinstance(version, (bool, np.bool_)) or version != SCHEMA_VERSION:  # true == 1
        found = "no schema_version" if version is None else \
            f"unsupported schema_version {version!r}"
        raise ValueError(f"{source}: {found} (this version reads {SCHEMA_VERSION})")
    missing = [k for k in ("mean_m", "sigma_m", "valid") if k not in data]
    if missing:
        raise ValueError(f"{source}: missing keys {missing} (and no driver fields "
                         f"{list(_DRIVER_FIELDS)})")
    arrays = {}
    for key in ("mean_m", "sigma_m"):
        arr = _float_array(data[key], source, key)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{source}: {key} has NaN or infinite values at zones "
                             f"{np.flatnonzero(~np.isfinite(arr)).tolist()}")
        if np.any(arr < 0):
            raise ValueError(f"{source}: {key} has negative values at zones "
                             f"{np.flatnonzero(arr < 0).tolist()}")
        arrays[key] = arr
    valid = _bool_array(data["valid"], source, "valid")
    count = arrays["mean_m"].size
    declared = data.get("zone_count", count)
    if isinstance(declared, (bool, np.bool_)) or not isinstance(declared, (int, np.integer)):
        raise ValueError(f"{source}: zone_count must be an integer, got {declared!r}")
    for key, arr in (("sigma_m", arrays["sigma_m"]), ("valid", valid)):
        if arr.size != count:
            raise ValueError(f"{source}: {key} has {arr.size} zones but mean_m has {count}")
    if declared != count or count not in (16, 64):
        raise ValueError(f"{source}: wrong zone count: zone_count={declared}, mean_m has "
                         f"{count} entries; expected 16 or 64")
    status = None
    if data.get("status") is not None:
        status = _float_array(data["status"], source, "status")
        if status.size != count or np.any((status < 0) | (status > 255)) or \
                np.any(status != np.round(status)):
            raise ValueError(f"{source}: status must hold {count} integer codes in 0..255")
    no_target = None
    if data.get("no_target") is not None:
        no_target = _bool_array(data["no_target"], source, "no_target", count)
    edges = counts = None
    if data.get("hist_counts") is not None or data.get("hist_edges_m") is not None:
        edges = _float_array(data.get("hist_edges_m"), source, "hist_edges_m")
        number_array(data.get("hist_counts"), f"{source}: hist_counts")
        counts = np.asarray(data.get("hist_counts"), dtype=np.float64)
        if counts.ndim != 2 or counts.shape[0] != count:
            raise ValueError(f"{source}: hist_counts must be ({count}, bins), "
                             f"got shape {counts.shape}")
        if not np.all(np.isfinite(counts)) or not np.all(np.isfinite(edges)):
            raise ValueError(f"{source}: histogram has NaN or infinite values")
    timestamp = _optional_float(data.get("timestamp_s"), source, "timestamp_s")
    targets = _target_arrays(data, source, count)
    try:
        frame = ZoneFrame(mean_m=arrays["mean_m"], sigma_m=arrays["sigma_m"],
                          valid=valid, status=status, hist_edges_m=edges,
                          hist_counts=counts, timestamp_s=timestamp, sensor_model=sensor_model,
                          no_target=no_target, **targets)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from err
    problem = frame.physical_error()
    if problem is not None:
        raise ValueError(f"{source}: {problem}")
    return frame


def _target_arrays(data: Mapping[str, Any], source: str, count: int) -> dict[str, Any]:
    """The optional target keys of a schema dict as ``ZoneFrame`` arguments ({} when absent).

    Raises:
        ValueError: naming ``source`` and the key: a partial set, arrays that are not
            (``count``, T) with T = ``targets_per_zone``, non-numbers, NaN or negative values.
    """
    present = [key for key in (*_TARGET_KEYS, "targets_per_zone", "target_order")
               if data.get(key) is not None]
    if not present:
        return {}
    missing = [key for key in ("target_mean_m", "target_sigma_m", "target_valid",
                               "targets_per_zone") if data.get(key) is None]
    if missing:
        raise ValueError(f"{source}: target keys {present} need {missing} as well")
    per_zone = data["targets_per_zone"]
    if isinstance(per_zone, (bool, np.bool_)) or not isinstance(per_zone, (int, np.integer)) \
            or not 1 <= per_zone <= 4:
        raise ValueError(f"{source}: targets_per_zone must be an integer in 1..4, got "
                         f"{per_zone!r}")
    out: dict[str, Any] = {}
    for key in _TARGET_KEYS:
        if data.get(key) is None:
            continue
        if key == "target_valid":
            values = _bool_array(data[key], source, key, count * int(per_zone))
        else:
            values = _float_array(data[key], source, key)
            if values.size == count * per_zone and not np.all(np.isfinite(values)):
                raise ValueError(f"{source}: {key} has NaN or infinite values")
            if np.any(values < 0):
                raise ValueError(f"{source}: {key} has negative values")
        if values.size != count * per_zone or np.ndim(data[key]) not in (1, 2) or (
                np.ndim(data[key]) == 2 and np.shape(data[key]) != (count, per_zone)):
            raise ValueError(f"{source}: {key} must be ({count}, {per_zone}) (zones x "
                             f"targets_per_zone), got shape {np.shape(data[key])}")
        out[key] = values.reshape(count, int(per_zone))
    order = data.get("target_order", "strongest")
    if not isinstance(order, str):
        raise ValueError(f"{source}: target_order must be a string, got {order!r}")
    out["target_order"] = order
    return out


def _bool_array(values: Any, source: str, key: str, count: int | None = None) -> np.ndarray:
    """Flat bool array of JSON booleans or 1/0 (``count`` of them when given).

    Raises:
        ValueError: ``"<source>: <key> must hold [<count>] booleans (true/false or 1/0)"``.
    """
    flags = np.asarray(values).reshape(-1)
    if (count is not None and flags.size != count) or (flags.dtype != bool and (
            flags.dtype.kind not in "iu" or not np.all(np.isin(flags, (0, 1))))):
        what = "booleans" if count is None else f"{count} booleans"
        raise ValueError(f"{source}: {key} must hold {what} (true/false or 1/0)")
    return flags.astype(bool)


def save_zone_frame(path: str | os.PathLike, frame: ZoneFrame, *,
                    overwrite: bool = False) -> Path:
    """Write ``frame`` atomically as ``.json`` or ``.npz`` (chosen by the suffix).

    Args:
        path: destination ending in ``.json`` or ``.npz``.
        frame: the zone frame (metres).
        overwrite: replace an existing file (default: refuse with ``FileExistsError``).

    Returns:
        The written path.

    Raises:
        ValueError: a frame its reader would refuse (:func:`check_writable`).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    data = zone_frame_to_dict(check_writable(frame))
    if suffix == ".json":
        return write_text_atomic(path, json.dumps(data, allow_nan=False) + "\n",
                                 overwrite=overwrite)
    if suffix == ".npz":
        arrays = {k: np.asarray(v) for k, v in data.items() if v is not None}
        with atomic_path(path, overwrite=overwrite) as tmp:
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            tmp.write_bytes(buffer.getvalue())
        return path
    raise ValueError(f"path must end in .json or .npz, got {path}")


def load_zone_frame(path: str | os.PathLike, *, orientation: Orientation | None = None,
                    ) -> ZoneFrame:
    """Read a zone frame from ``.json`` (schema or raw driver dump) or ``.npz``.

    Args:
        path: the file.
        orientation: for raw driver dumps, how the driver grid maps onto the image.

    Raises:
        FileNotFoundError / IsADirectoryError: the path is missing or a folder.
        ValueError: corrupt or truncated file, or invalid content; the message names the
            file (an :class:`~deltar.io.input_file.InputFileError` when it is unreadable).
    """
    path = input_file(path, "zone frame file")
    suffix = path.suffix.lower()
    if suffix not in (".json", ".npz"):
        raise ValueError(f"{path}: unknown zone frame format (expected .json or .npz)")
    with reading(path, "zone frame file"):
        if suffix == ".json":
            data = read_json(path, "zone frame file")
        else:
            with np.load(path, allow_pickle=False) as npz:
                data = {k: npz[k] for k in npz.files}
            data = {k: (v.item() if v.ndim == 0 else v) for k, v in data.items()}
        return zone_frame_from_dict(data, source=str(path), orientation=orientation)


def zone_frame_from_driver_result(result: Any, *, orientation: Orientation | None = None,
                                  timestamp_s: float | None = None,
                                  sensor_model: str = "VL53L5CX", grid: int | None = None,
                                  targets_per_zone: int | None = None,
                                  target_order: str = "strongest") -> ZoneFrame:
    """Convert what a Python driver returns (dict or results object) into a ``ZoneFrame``.

    Works with ``vl53l5cx-ctypes`` results, SparkFun's ``RangingDataResults`` and
    CircuitPython's ``get_ranging_data()``: anything with ``distance_mm``,
    ``range_sigma_mm`` and ``target_status`` as items or attributes (flat, millimetres),
    and optionally ``nb_target_detected`` (one per zone) and ``signal_per_spad`` (like
    ``distance_mm``, kcps per SPAD). ``grid``, ``targets_per_zone`` and ``target_order``
    are as the driver was configured (see :meth:`ZoneFrame.from_driver`; inferred from
    the lengths when None). ``signal_per_spad`` is read only when the frame holds every
    target (``targets_per_zone`` given, or more entries than zones), as
    ``target_signal``; a single-target reading has no use for it.
    """
    fields = {}
    for name in (*_DRIVER_FIELDS, "nb_target_detected", "signal_per_spad"):
        if isinstance(result, Mapping):
            value = result.get(name)
        else:
            value = getattr(result, name, None)
        if value is None and name in _DRIVER_FIELDS:
            raise ValueError(f"driver result has no field {name!r}")
        if value is None or isinstance(value, np.ndarray):
            fields[name] = value
            continue
        try:  # ctypes arrays, array.array, lists, tuples
            fields[name] = list(value)
        except TypeError:
            raise ValueError(f"driver result field {name!r} must be a list of numbers, got "
                             f"{type(value).__name__} {value!r}") from None
    several = targets_per_zone is not None or np.size(fields["distance_mm"]) not in (16, 64)
    return ZoneFrame.from_driver(fields["distance_mm"], fields["range_sigma_mm"],
                                 fields["target_status"], orientation=orientation,
                                 timestamp_s=timestamp_s, sensor_model=sensor_model, grid=grid,
                                 nb_target_detected=fields["nb_target_detected"],
                                 targets_per_zone=targets_per_zone, target_order=target_order,
                                 signal_per_spad=fields["signal_per_spad"] if several else None)


def _float_array(values: Any, source: str, key: str) -> np.ndarray:
    return number_array(values, f"{source}: {key}")


def _optional_float(value: Any, source: str, key: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise ValueError(f"{source}: {key} must be a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ValueError(f"{source}: {key} must be finite, got {value!r}")
    return out
