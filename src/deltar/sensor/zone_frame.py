"""The zone frame: one reading of a multi-zone ToF sensor (VL53L5CX / VL53L8CX)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from deltar.sensor.zone_targets import (
    check_target_fields,
    convert_target_fields,
    driver_readings,
)
from deltar.sensor.zone_values import (
    DEFAULT_VALID_STATUS,
    NO_TARGET_STATUS,
    SUPPORTED_GRIDS,
    UNKNOWN_MODEL_MAX_RANGE_M,  # noqa: F401  (its home before zone_values)
    checked_range_m,
    flags,
    grid_from_count,
    numbers,
    sensor_max_range_m,
    status_codes,
)

__all__ = ["NO_TARGET_DEPTH_M", "Orientation", "ZoneFrame", "no_target_as_readings"]

#: Where the methods that use the flag place a zone that reported no target, metres:
#: beyond the 4 m range, at 1.25 times it (a prior, not fitted to any scene).
NO_TARGET_DEPTH_M = 5.0


def no_target_as_readings(zone_mean_m: np.ndarray, zone_valid: np.ndarray,
                          zone_no_target: np.ndarray, far_depth_m: float = NO_TARGET_DEPTH_M
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Zones that reported no target, and are not valid, as readings at ``far_depth_m``.

    The rule every method that uses the flag applies to the zone readings (the ``+far``
    baselines, the estimator's confidence blend).

    Args:
        zone_mean_m: (Z,) zone readings, metres.
        zone_valid: (Z,) bool.
        zone_no_target: (Z,) bool, the zones' no-target flags.
        far_depth_m: the depth such a zone reads at, metres.

    Returns:
        ``(mean_m, valid)``: (Z,) float readings with those zones at ``far_depth_m`` and
        (Z,) bool validity including them.
    """
    valid = np.asarray(zone_valid, dtype=bool)
    far = np.asarray(zone_no_target, dtype=bool) & ~valid
    return np.where(far, far_depth_m, zone_mean_m), valid | far



@dataclass(frozen=True)
class Orientation:
    """How the driver's zone grid maps onto the image grid.

    Applied to the driver's ``(n, n)`` row-major grid in this order: up-down flip,
    left-right flip, then ``rot90`` quarter turns counter-clockwise (``numpy.rot90``).
    The identity leaves zone ``r * n + c`` at image row ``r``, column ``c``.
    """

    flip_ud: bool = False
    flip_lr: bool = False
    rot90: int = 0

    def __post_init__(self) -> None:
        # A string flag ("no") is truthy and rot90=1.5 turns like 3 in numpy: refuse both.
        for name in ("flip_ud", "flip_lr"):
            value = getattr(self, name)
            if not isinstance(value, (bool, np.bool_)):
                raise ValueError(f"Orientation.{name} must be True or False, got {value!r}")
        if isinstance(self.rot90, (bool, np.bool_)) or not isinstance(
                self.rot90, (int, np.integer)):
            raise ValueError(f"Orientation.rot90 must be an integer number of quarter "
                             f"turns, got {self.rot90!r}")

    def apply(self, grid: np.ndarray) -> np.ndarray:
        """Reorient an array whose first two axes are the ``(n, n)`` zone grid."""
        out = grid
        if self.flip_ud:
            out = out[::-1]
        if self.flip_lr:
            out = out[:, ::-1]
        if self.rot90 % 4:
            out = np.rot90(out, k=self.rot90 % 4, axes=(0, 1))
        return np.ascontiguousarray(out)


@dataclass
class ZoneFrame:
    """One multi-zone ToF reading on an ``n x n`` grid (n = 4 or 8), in image orientation.

    Zone ``(r, c)`` is row ``r`` (top to bottom) and column ``c`` (left to right) of the grid
    as it appears in the image; flat zone index ``r * n + c`` (row-major).

    Attributes:
        mean_m: (n, n) float32, per-zone distance in metres (meaningless where not valid).
        sigma_m: (n, n) float32, per-zone standard deviation in metres (>= 0 where valid).
        valid: (n, n) bool, zones that carry a measurement.
        status: optional (n, n) uint8, the driver's raw ``target_status`` codes.
        hist_edges_m: optional (B + 1,) float32 histogram bin edges in metres, increasing.
        hist_counts: optional (n, n, B) float32 per-zone histogram counts (for sensors that
            report one, e.g. ST's CH parts).
        timestamp_s: optional capture time in seconds (any monotonic clock).
        sensor_model: free text, e.g. ``"VL53L5CX"``.
        no_target: optional (n, n) bool, invalid zones that reported *no target*
            (nothing within the sensor's range, so the surface is farther away); by
            default the zones whose ``status`` is 255 (:data:`NO_TARGET_STATUS`), or none.
        target_mean_m: optional (n, n, T) float32, every target the zone reported,
            metres, T = 1..4 (:data:`MAX_TARGETS_PER_ZONE`), in ``target_order``; 0
            where not valid. Given together with ``target_sigma_m`` and
            ``target_valid``; None for a frame with only the primary reading.
        target_sigma_m: optional (n, n, T) float32 standard deviations, metres.
        target_valid: optional (n, n, T) bool, the targets that carry a measurement.
        target_status: optional (n, n, T) uint8, the driver's ``target_status`` per target.
        target_signal: optional (n, n, T) float32 >= 0, each target's return signal (ST:
            ``signal_per_spad``, kcps per SPAD; the simulator: the target's share of the
            zone's pixels over its squared distance in metres). Only ratios within a zone
            are used: with equal reflectance a target's share of the zone is
            proportional to ``signal * distance^2`` (:mod:`deltar.sensor.targets`).
        target_order: ``"strongest"`` (the driver's default: strongest return first) or
            ``"closest"`` (closest first). In ``"strongest"`` order target 0 is the primary
            reading: ``target_valid[..., 0] == valid`` and, where valid, the target's mean
            and sigma equal ``mean_m`` and ``sigma_m`` (checked).
    """

    mean_m: np.ndarray
    sigma_m: np.ndarray
    valid: np.ndarray
    status: np.ndarray | None = None
    hist_edges_m: np.ndarray | None = None
    hist_counts: np.ndarray | None = None
    timestamp_s: float | None = None
    sensor_model: str = "VL53L5CX"
    extra: dict = field(default_factory=dict)
    no_target: np.ndarray | None = None
    target_mean_m: np.ndarray | None = None
    target_sigma_m: np.ndarray | None = None
    target_valid: np.ndarray | None = None
    target_status: np.ndarray | None = None
    target_order: str = "strongest"
    target_signal: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Numbers stay numbers: strings and booleans are refused, never converted.
        self.mean_m = numbers(self.mean_m, "ZoneFrame.mean_m").astype(np.float32)
        self.sigma_m = numbers(self.sigma_m, "ZoneFrame.sigma_m").astype(np.float32)
        self.valid = flags(self.valid, "ZoneFrame.valid")
        if self.status is not None:
            self.status = status_codes(self.status, "ZoneFrame.status")
        if self.mean_m.ndim == 1:  # flat row-major input
            n = grid_from_count(self.mean_m.size, "mean_m")
            self.mean_m = self.mean_m.reshape(n, n)
            self.sigma_m = self.sigma_m.reshape(n, n) if self.sigma_m.size == n * n \
                else self.sigma_m
            self.valid = self.valid.reshape(n, n) if self.valid.size == n * n else self.valid
            if self.status is not None:
                self.status = np.asarray(self.status).reshape(n, n)
            if self.no_target is not None and np.asarray(self.no_target).size == n * n:
                self.no_target = np.asarray(self.no_target).reshape(n, n)
            if self.hist_counts is not None:
                self.hist_counts = np.asarray(self.hist_counts).reshape(n, n, -1)
        convert_target_fields(self)
        if self.no_target is None and self.status is not None:
            status = np.asarray(self.status)
            if status.shape == self.valid.shape:
                self.no_target = (status == NO_TARGET_STATUS) & ~self.valid
        self.validate()

    # ------------------------------------------------------------------ checks
    @property
    def grid(self) -> int:
        """Zones per side (4 or 8)."""
        return int(self.mean_m.shape[0])

    @property
    def zone_count(self) -> int:
        """Zones in the frame: 16 or 64 (``grid`` squared)."""
        return self.grid * self.grid

    def validate(self) -> None:
        """Raise ``ValueError`` naming the field if the frame is inconsistent."""
        n = self.mean_m.shape[0] if self.mean_m.ndim == 2 else -1
        if self.mean_m.ndim != 2 or self.mean_m.shape != (n, n) or n not in SUPPORTED_GRIDS:
            raise ValueError(f"ZoneFrame.mean_m must have shape (n, n) with n in "
                             f"{SUPPORTED_GRIDS}, got {self.mean_m.shape}")
        for name in ("sigma_m", "valid"):
            arr = getattr(self, name)
            if arr.shape != (n, n):
                raise ValueError(f"ZoneFrame.{name} must have shape ({n}, {n}) like mean_m, "
                                 f"got {arr.shape}")
        if self.status is not None:
            self.status = status_codes(self.status, "ZoneFrame.status")
            if self.status.shape != (n, n):
                raise ValueError(f"ZoneFrame.status must have shape ({n}, {n}), "
                                 f"got {self.status.shape}")
            contradiction = np.flatnonzero((self.valid & (self.status == NO_TARGET_STATUS))
                                           .reshape(-1))
            if contradiction.size:
                raise ValueError(f"ZoneFrame zones {contradiction[:5].tolist()} are valid but "
                                 f"their status is {NO_TARGET_STATUS} (no target); a zone "
                                 "either reads a distance or reports no target")
        if self.no_target is not None:
            flags = np.asarray(self.no_target)
            if flags.dtype != bool and not np.isin(flags, (0, 1)).all():
                raise ValueError("ZoneFrame.no_target must be boolean")
            self.no_target = flags.astype(bool)
            if self.no_target.shape != (n, n):
                raise ValueError(f"ZoneFrame.no_target must have shape ({n}, {n}), "
                                 f"got {self.no_target.shape}")
            if np.any(self.no_target & self.valid):
                raise ValueError("ZoneFrame.no_target marks valid zones "
                                 f"{np.argwhere(self.no_target & self.valid).tolist()}; a "
                                 "zone either reads a distance or reports no target")
        v = self.valid
        if not np.all(np.isfinite(self.mean_m[v])):
            raise ValueError("ZoneFrame.mean_m has NaN or infinite values in valid zones "
                             f"{np.argwhere(v & ~np.isfinite(self.mean_m)).tolist()}")
        if np.any(self.mean_m[v] < 0):
            raise ValueError("ZoneFrame.mean_m has negative distances in valid zones "
                             f"{np.argwhere(v & (self.mean_m < 0)).tolist()}")
        bad_sigma = v & ~(np.isfinite(self.sigma_m) & (self.sigma_m >= 0))
        if np.any(bad_sigma):
            raise ValueError("ZoneFrame.sigma_m must be finite and >= 0 in valid zones, bad "
                             f"zones {np.argwhere(bad_sigma).tolist()}")
        if (self.hist_counts is None) != (self.hist_edges_m is None):
            raise ValueError("ZoneFrame.hist_counts and hist_edges_m must be given together")
        if self.hist_counts is not None:
            self.hist_counts = np.asarray(self.hist_counts, dtype=np.float32)
            self.hist_edges_m = np.asarray(self.hist_edges_m, dtype=np.float32)
            bins = self.hist_edges_m.size - 1
            if self.hist_edges_m.ndim != 1 or bins < 1 or \
                    not np.all(np.isfinite(self.hist_edges_m)) or \
                    not np.all(np.diff(self.hist_edges_m) > 0):  # NaN compares False
                raise ValueError("ZoneFrame.hist_edges_m must be 1-D, finite and strictly "
                                 "increasing (metres)")
            if self.hist_counts.shape != (n, n, bins):
                raise ValueError(f"ZoneFrame.hist_counts must have shape ({n}, {n}, {bins}), "
                                 f"got {self.hist_counts.shape}")
            if not np.all(np.isfinite(self.hist_counts)) or np.any(self.hist_counts < 0):
                raise ValueError("ZoneFrame.hist_counts must be finite and >= 0")
        if self.timestamp_s is not None and (
                isinstance(self.timestamp_s, (bool, np.bool_))
                or not isinstance(self.timestamp_s, (int, float, np.integer, np.floating))
                or not math.isfinite(float(self.timestamp_s))):
            raise ValueError(f"ZoneFrame.timestamp_s must be a finite number of seconds, got "
                             f"{self.timestamp_s!r}")
        if not isinstance(self.sensor_model, str):
            raise ValueError(f"ZoneFrame.sensor_model must be a string, got "
                             f"{self.sensor_model!r}")
        check_target_fields(self, n)

    @property
    def targets_per_zone(self) -> int:
        """T, the number of target slots per zone (1 for a frame without target arrays)."""
        return 1 if self.target_mean_m is None else int(self.target_mean_m.shape[2])

    def targets(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every target of every zone: mean (n, n, T) float32 metres, sigma (n, n, T)
        float32 metres, valid (n, n, T) bool, in :attr:`target_order`.

        A frame without target arrays gives T = 1: the primary reading (zeros where
        not valid).
        """
        if self.target_mean_m is not None:
            return self.target_mean_m, self.target_sigma_m, self.target_valid
        valid = self.valid[..., None]
        return (np.where(valid, self.mean_m[..., None], np.float32(0.0)),
                np.where(valid, self.sigma_m[..., None], np.float32(0.0)), valid.copy())

    def flat_targets(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`targets` as row-major (Z, T) arrays, Z = n * n."""
        return tuple(a.reshape(self.zone_count, -1) for a in self.targets())

    # ------------------------------------------------------------------ views
    def flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row-major flat views: mean (Z,), sigma (Z,), valid (Z,) with Z = n * n."""
        return self.mean_m.reshape(-1), self.sigma_m.reshape(-1), self.valid.reshape(-1)

    def flat_no_target(self) -> np.ndarray:
        """(Z,) bool row-major no-target flags (all False when the frame has none)."""
        if self.no_target is None:
            return np.zeros(self.zone_count, dtype=bool)
        return self.no_target.reshape(-1)

    def range_limit_m(self, max_range_m: float | None = None) -> float:
        """The largest distance the frame's sensor can read, metres: ``max_range_m`` when
        given, else the sensor model's (:data:`SENSOR_MAX_RANGE_M`; infinite for unknown
        models)."""
        return sensor_max_range_m(self.sensor_model) if max_range_m is None else max_range_m

    def _checked_limit_m(self, max_range_m: float | None) -> float:
        """:meth:`range_limit_m` for the physical checks
        (:func:`~deltar.sensor.zone_values.checked_range_m`: an unknown model is still
        held to :data:`UNKNOWN_MODEL_MAX_RANGE_M`)."""
        return checked_range_m(self.sensor_model, max_range_m)

    def out_of_range(self, max_range_m: float | None = None) -> np.ndarray:
        """Valid zones whose distance is physically impossible for the sensor.

        Args:
            max_range_m: largest possible distance in metres; by default the sensor
                model's (:data:`SENSOR_MAX_RANGE_M`; :data:`UNKNOWN_MODEL_MAX_RANGE_M` for
                unknown models).

        Returns:
            (n, n) bool, True where a zone is flagged valid but reads ``d <= 0`` or
            ``d > max_range_m``.
        """
        limit = self._checked_limit_m(max_range_m)
        return self.valid & ((self.mean_m <= 0) | (self.mean_m > limit))

    def range_error(self, max_range_m: float | None = None) -> str | None:
        """Why the frame's valid zones are out of range, or None when they are not.

        The message names the zones (flat row-major indices, at most five), their
        readings and the accepted range.
        """
        bad = np.flatnonzero(self.out_of_range(max_range_m).reshape(-1))
        if bad.size == 0:
            return None
        limit = self._checked_limit_m(max_range_m)
        readings = ", ".join(f"{self.mean_m.reshape(-1)[i]:.6g}" for i in bad[:5])
        more = f" and {bad.size - 5} more" if bad.size > 5 else ""
        return (f"{bad.size} valid zone(s) read distances outside the {self.sensor_model} "
                f"range 0 < d <= {limit:g} m (zones {bad[:5].tolist()}{more}: {readings} m); "
                "mark such zones invalid")

    def physical_error(self, max_range_m: float | None = None) -> str | None:
        """Why the frame's valid zones cannot be a real reading, or None when they can.

        One place for the physical checks of a reading (besides :meth:`validate`'s
        consistency checks): a valid zone must read ``0 < d <= range``
        (:meth:`range_error`), have a sigma no larger than the range (a spread of
        distances within it cannot be larger), and, with histograms, have counted
        some photons; a valid target (``target_mean_m`` ...) must read ``0 < d <=
        range`` with a sigma no larger than the range.

        Args:
            max_range_m: the largest possible distance in metres; by default the sensor
                model's (:data:`SENSOR_MAX_RANGE_M`; :data:`UNKNOWN_MODEL_MAX_RANGE_M` for
                unknown models).

        Returns:
            The first problem, naming the zones (flat row-major indices, at most five)
            and their values, or None.
        """
        mean, sigma, valid = self.flat()
        # Arrays written into after construction skip validate(): NaN compares False.
        broken = np.flatnonzero(valid & ~(np.isfinite(mean) & np.isfinite(sigma)))
        if broken.size:
            return (f"{broken.size} valid zone(s) have a NaN or infinite mean or sigma "
                    f"(zones {broken[:5].tolist()}); mark such zones invalid")
        problem = self.range_error(max_range_m)
        if problem is not None:
            return problem
        limit = self._checked_limit_m(max_range_m)
        wide = np.flatnonzero(valid & (sigma > limit))
        if wide.size:
            values = ", ".join(f"{sigma[i]:.6g}" for i in wide[:5])
            return (f"{wide.size} valid zone(s) have a sigma larger than the {self.sensor_model} "
                    f"range {limit:g} m (zones {wide[:5].tolist()}: {values} m), which no "
                    "reading within the range can have; mark such zones invalid")
        if self.hist_counts is not None:
            counts = self.hist_counts.reshape(self.zone_count, -1)
            empty = np.flatnonzero(valid & ~np.any(counts > 0, axis=1))
            if empty.size:
                return (f"{empty.size} valid zone(s) have an all-zero histogram (zones "
                        f"{empty[:5].tolist()}): a zone that counted no photons measured no "
                        "distance; mark such zones invalid")
        if self.target_mean_m is not None:
            mean_t, sigma_t, valid_t = self.flat_targets()
            bad = valid_t & ((mean_t <= 0) | (mean_t > limit) | (sigma_t > limit))
            if bad.any():
                zones, targets = np.nonzero(bad)
                where = ", ".join(f"zone {z} target {t}: {mean_t[z, t]:.6g} m, sigma "
                                  f"{sigma_t[z, t]:.6g} m" for z, t in
                                  zip(zones[:5], targets[:5], strict=True))
                return (f"{int(bad.sum())} valid target(s) read distances outside the "
                        f"{self.sensor_model} range 0 < d <= {limit:g} m or have a sigma "
                        f"larger than it ({where}); mark such targets invalid")
        return None

    @property
    def valid_count(self) -> int:
        """Number of valid zones."""
        return int(np.count_nonzero(self.valid))

    def mean_sigma(self) -> np.ndarray:
        """(Z, 2) float32 of [mean, sigma] in metres, zeros in invalid zones (ZJU-L5 layout)."""
        mean, sigma, valid = self.flat()
        out = np.stack([mean, sigma], axis=1).astype(np.float32)
        out[~valid] = 0.0
        return out

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_driver(
        cls,
        distance_mm: Sequence[float],
        range_sigma_mm: Sequence[float],
        target_status: Sequence[int],
        *,
        grid: int | None = None,
        valid_status: Sequence[int] = DEFAULT_VALID_STATUS,
        orientation: Orientation | None = None,
        timestamp_s: float | None = None,
        sensor_model: str = "VL53L5CX",
        nb_target_detected: Sequence[int] | None = None,
        targets_per_zone: int | None = None,
        target_order: str = "strongest",
        signal_per_spad: Sequence[float] | None = None,
    ) -> ZoneFrame:
        """Build a frame from what the Python drivers return.

        The driver's flat lists (millimetres, ``zones * T`` entries zone-major for a build
        with T targets per zone; the primary reading is each zone's first target) as
        :func:`~deltar.sensor.zone_targets.driver_readings` reads them: every argument
        but ``timestamp_s`` (capture time in seconds) is documented there.

        Raises:
            ValueError: lengths that do not fit ``grid`` and ``targets_per_zone``, codes
                that are not integers in 0..255, an unknown ``target_order``, naming the
                argument.
        """
        fields = driver_readings(
            distance_mm, range_sigma_mm, target_status, grid=grid, valid_status=valid_status,
            orientation=orientation, sensor_model=sensor_model,
            nb_target_detected=nb_target_detected, targets_per_zone=targets_per_zone,
            target_order=target_order, signal_per_spad=signal_per_spad)
        return cls(**fields, timestamp_s=timestamp_s, sensor_model=sensor_model)
