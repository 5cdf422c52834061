"""The zone frame: one reading of a multi-zone ToF sensor (VL53L5CX / VL53L8CX)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

#: Target status codes that ST documents as a valid range (5: valid, 9: valid, large pulse).
DEFAULT_VALID_STATUS: tuple[int, ...] = (5, 9)
#: ST's "no target detected": nothing returned within the sensor's range.
NO_TARGET_STATUS = 255
#: Where the methods that use the flag place a zone that reported no target, metres:
#: beyond the 4 m range, at 1.25 times it (a prior, not fitted to any scene).
NO_TARGET_DEPTH_M = 5.0
#: Most targets per zone ST's driver reports (``VL53L5CX_NB_TARGET_PER_ZONE``, 1 to 4).
MAX_TARGETS_PER_ZONE = 4
#: Orders the driver reports a zone's targets in: strongest return first (the default)
#: or closest first (``vl53l5cx_set_target_order``).
TARGET_ORDERS: tuple[str, ...] = ("strongest", "closest")


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


SUPPORTED_GRIDS: tuple[int, ...] = (4, 8)

#: Largest distance each sensor model reports, metres (ST datasheets: "up to 4 m").
#: A valid zone must read ``0 < d <= range``; unknown models have no upper limit.
SENSOR_MAX_RANGE_M: dict[str, float] = {"VL53L5CX": 4.0, "VL53L8CX": 4.0}


def sensor_max_range_m(sensor_model: str) -> float:
    """The largest distance ``sensor_model`` reports, metres (``inf`` when unknown)."""
    return SENSOR_MAX_RANGE_M.get(str(sensor_model).upper(), math.inf)


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

    def __post_init__(self) -> None:
        # Numbers stay numbers: strings and booleans are refused, never converted.
        self.mean_m = _numbers(self.mean_m, "ZoneFrame.mean_m").astype(np.float32)
        self.sigma_m = _numbers(self.sigma_m, "ZoneFrame.sigma_m").astype(np.float32)
        self.valid = _flags(self.valid, "ZoneFrame.valid")
        if self.status is not None:
            self.status = status_codes(self.status, "ZoneFrame.status")
        if self.mean_m.ndim == 1:  # flat row-major input
            n = _grid_from_count(self.mean_m.size, "mean_m")
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
        self._convert_targets()
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
        if not np.all(np.isfinite(self.sigma_m[v])) or np.any(self.sigma_m[v] < 0):
            raise ValueError("ZoneFrame.sigma_m must be finite and >= 0 in valid zones, bad "
                             f"zones {np.argwhere(v & ~(self.sigma_m >= 0)).tolist()}")
        if (self.hist_counts is None) != (self.hist_edges_m is None):
            raise ValueError("ZoneFrame.hist_counts and hist_edges_m must be given together")
        if self.hist_counts is not None:
            self.hist_counts = np.asarray(self.hist_counts, dtype=np.float32)
            self.hist_edges_m = np.asarray(self.hist_edges_m, dtype=np.float32)
            bins = self.hist_edges_m.size - 1
            if self.hist_edges_m.ndim != 1 or bins < 1 or np.any(np.diff(self.hist_edges_m) <= 0):
                raise ValueError("ZoneFrame.hist_edges_m must be 1-D and strictly increasing")
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
        self._validate_targets(n)

    def _convert_targets(self) -> None:
        """Target arrays as float32 / bool / uint8, (Z, T) flat input as (n, n, T)."""
        given = [name for name in ("target_mean_m", "target_sigma_m", "target_valid")
                 if getattr(self, name) is not None]
        if given and len(given) < 3:
            raise ValueError("ZoneFrame.target_mean_m, target_sigma_m and target_valid must "
                             f"be given together, got only {given}")
        if not given:
            if self.target_status is not None:
                raise ValueError("ZoneFrame.target_status needs target_mean_m, "
                                 "target_sigma_m and target_valid")
            return
        self.target_mean_m = _numbers(self.target_mean_m,
                                      "ZoneFrame.target_mean_m").astype(np.float32)
        self.target_sigma_m = _numbers(self.target_sigma_m,
                                       "ZoneFrame.target_sigma_m").astype(np.float32)
        self.target_valid = _flags(self.target_valid, "ZoneFrame.target_valid")
        if self.target_status is not None:
            self.target_status = status_codes(self.target_status, "ZoneFrame.target_status")
        n = self.mean_m.shape[0] if self.mean_m.ndim == 2 else -1
        for name in ("target_mean_m", "target_sigma_m", "target_valid", "target_status"):
            arr = getattr(self, name)
            if arr is not None and arr.ndim == 2 and n > 0 and arr.shape[0] == n * n:
                setattr(self, name, arr.reshape(n, n, arr.shape[1]))
        # Targets that are not valid carry 0, as invalid zones do in files.
        if self.target_valid.shape == self.target_mean_m.shape:
            self.target_mean_m = np.where(self.target_valid, self.target_mean_m,
                                          np.float32(0.0))
        if self.target_valid.shape == self.target_sigma_m.shape:
            self.target_sigma_m = np.where(self.target_valid, self.target_sigma_m,
                                           np.float32(0.0))

    def _validate_targets(self, n: int) -> None:
        """The checks of the target arrays (see the class doc), ValueErrors naming the field."""
        if self.target_order not in TARGET_ORDERS:
            raise ValueError(f"ZoneFrame.target_order must be one of {TARGET_ORDERS}, got "
                             f"{self.target_order!r}")
        if self.target_mean_m is None:
            return
        mean = self.target_mean_m
        if mean.ndim != 3 or mean.shape[:2] != (n, n) or \
                not 1 <= mean.shape[2] <= MAX_TARGETS_PER_ZONE:
            raise ValueError(f"ZoneFrame.target_mean_m must have shape ({n}, {n}, T) with "
                             f"T in 1..{MAX_TARGETS_PER_ZONE}, got {mean.shape}")
        for name in ("target_sigma_m", "target_valid", "target_status"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != mean.shape:
                raise ValueError(f"ZoneFrame.{name} must have shape {mean.shape} like "
                                 f"target_mean_m, got {arr.shape}")
        valid = self.target_valid
        sigma = self.target_sigma_m
        if not np.all(np.isfinite(mean[valid])) or np.any(mean[valid] < 0):
            raise ValueError("ZoneFrame.target_mean_m must be finite and >= 0 in valid "
                             "targets, bad (row, column, target) "
                             f"{np.argwhere(valid & ~(mean >= 0)).tolist()[:5]}")
        if not np.all(np.isfinite(sigma[valid])) or np.any(sigma[valid] < 0):
            raise ValueError("ZoneFrame.target_sigma_m must be finite and >= 0 in valid "
                             "targets, bad (row, column, target) "
                             f"{np.argwhere(valid & ~(sigma >= 0)).tolist()[:5]}")
        if self.target_status is not None and \
                np.any(valid & (self.target_status == NO_TARGET_STATUS)):
            raise ValueError(f"ZoneFrame.target_status is {NO_TARGET_STATUS} (no target) for "
                             "valid targets (row, column, target) "
                             f"{np.argwhere(valid & (self.target_status == 255)).tolist()[:5]}")
        if self.target_order == "strongest":
            # Target 0 is the primary reading: the same flags, and the same values where valid.
            differs = (valid[..., 0] != self.valid) | (self.valid & (
                (np.abs(mean[..., 0] - self.mean_m) > 1e-6)
                | (np.abs(sigma[..., 0] - self.sigma_m) > 1e-6)))
            if differs.any():
                raise ValueError("ZoneFrame.target_mean_m / target_sigma_m / target_valid "
                                 "[..., 0] must equal mean_m / sigma_m / valid in "
                                 "'strongest' order (target 0 is the primary reading); "
                                 f"they differ at zones {np.argwhere(differs).tolist()[:5]}")

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

    def out_of_range(self, max_range_m: float | None = None) -> np.ndarray:
        """Valid zones whose distance is physically impossible for the sensor.

        Args:
            max_range_m: largest possible distance in metres; by default the sensor
                model's (:data:`SENSOR_MAX_RANGE_M`, no limit for unknown models).

        Returns:
            (n, n) bool, True where a zone is flagged valid but reads ``d <= 0`` or
            ``d > max_range_m``.
        """
        limit = sensor_max_range_m(self.sensor_model) if max_range_m is None else max_range_m
        return self.valid & ((self.mean_m <= 0) | (self.mean_m > limit))

    def range_error(self, max_range_m: float | None = None) -> str | None:
        """Why the frame's valid zones are out of range, or None when they are not.

        The message names the zones (flat row-major indices, at most five), their
        readings and the accepted range.
        """
        bad = np.flatnonzero(self.out_of_range(max_range_m).reshape(-1))
        if bad.size == 0:
            return None
        limit = sensor_max_range_m(self.sensor_model) if max_range_m is None else max_range_m
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
                model's (:data:`SENSOR_MAX_RANGE_M`, no limit for unknown models).

        Returns:
            The first problem, naming the zones (flat row-major indices, at most five)
            and their values, or None.
        """
        problem = self.range_error(max_range_m)
        if problem is not None:
            return problem
        limit = sensor_max_range_m(self.sensor_model) if max_range_m is None else max_range_m
        _, sigma, valid = self.flat()
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
    ) -> ZoneFrame:
        """Build a frame from what the Python drivers return.

        Driver builds for several targets per zone (``VL53L5CX_NB_TARGET_PER_ZONE`` = T)
        return ``zones * T`` entries per field, zone-major: entry ``zone * T + t`` is
        target ``t`` of ``zone``. The primary reading (``mean_m``, ``sigma_m``, ``valid``)
        is each zone's first target; with T > 1 (or ``targets_per_zone`` given) the frame
        also holds every target (``target_mean_m`` ... (n, n, T)).

        Args:
            distance_mm: flat list of ``zones * T`` distances in millimetres (driver
                order). Targets reading 0 or less (error codes) or more than the sensor
                model's range (:data:`SENSOR_MAX_RANGE_M`, with a ``RuntimeWarning``) are
                invalid.
            range_sigma_mm: flat list of the same length, sigma in millimetres.
            target_status: flat list of the same length, ST's target status codes.
            grid: 4 or 8; inferred when None: from ``nb_target_detected``'s length when
                given, else from the length of ``distance_mm`` (16 -> 4, 64 -> 8, one
                target per zone).
            valid_status: status codes that count as a valid range (default 5 and 9).
            orientation: how the driver's grid maps onto the image (identity by default).
            timestamp_s: capture time in seconds.
            sensor_model: free text stored with the frame.
            nb_target_detected: optional flat list of ``zones`` counts (driver order), the
                number of targets each zone detected; target ``t`` of a zone is valid only
                when ``t`` is below its count (the driver leaves stale values beyond it).
            targets_per_zone: T, 1..4; inferred from the lengths when None (``len /
                zones``). A buffer sized for 8x8 (``64 * T``) read in 4x4 mode uses its
                first ``16 * T`` entries, as ST's driver fills it.
            target_order: ``"strongest"`` (the driver's default) or ``"closest"``, as
                the driver was configured (``vl53l5cx_set_target_order``).

        Raises:
            ValueError: lengths that do not fit ``grid`` and ``targets_per_zone``, codes
                that are not integers in 0..255, an unknown ``target_order``, naming the
                argument.
        """
        arrays = {}
        for name, values in (("distance_mm", distance_mm), ("range_sigma_mm", range_sigma_mm),
                             ("target_status", target_status)):
            arrays[name] = number_array(values, name)
        sizes = [arr.size for arr in arrays.values()]
        if len(set(sizes)) > 1:
            raise ValueError("distance_mm, range_sigma_mm and target_status must have the same "
                             f"length (one entry per zone and target), got {sizes}")
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
            n = grid
        elif detected is not None:
            n = _grid_from_count(detected.size, "nb_target_detected")
        elif targets_per_zone is not None and sizes[0] % targets_per_zone == 0:
            n = _grid_from_count(sizes[0] // targets_per_zone, "distance_mm")
        elif sizes[0] in (16, 64):
            n = _grid_from_count(sizes[0], "distance_mm")
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
                                 f"{zones} (one per zone of a {n}x{n} grid)")
        for name, arr in arrays.items():
            # Zone-major: target t of zone z at z * per_zone + t.
            arrays[name] = arr[: zones * per_zone].reshape(zones, per_zone)
        status = status_codes(arrays["target_status"], "target_status")
        valid = np.isin(status, np.asarray(valid_status, dtype=np.uint8))
        valid &= status != NO_TARGET_STATUS
        if detected is not None:
            valid &= np.arange(per_zone)[None, :] < detected[:, None]
        mean = arrays["distance_mm"] / 1000.0
        sigma = arrays["range_sigma_mm"] / 1000.0
        valid &= np.isfinite(mean) & np.isfinite(sigma) & (mean > 0) & (sigma >= 0)
        # Readings beyond the sensor's range are not measurements: invalid, visibly.
        limit = sensor_max_range_m(sensor_model)
        for far, what, values in ((valid & (mean > limit), "read more than", mean),
                                  (valid & (sigma > limit), "have a sigma larger than", sigma)):
            if far.any():
                unit = "zone(s)" if per_zone == 1 else "target(s)"
                warnings.warn(f"{int(far.sum())} {unit} with a valid status {what} the "
                              f"{sensor_model}'s {limit:g} m range (up to "
                              f"{values[far].max():.6g} m); marked invalid", RuntimeWarning,
                              stacklevel=2)
                valid &= ~far
        orient = orientation or Orientation()
        mean, sigma, valid, status = (orient.apply(a.reshape(n, n, per_zone))
                                      for a in (mean, sigma, valid, status))
        mean = np.where(valid, mean, 0.0).astype(np.float32)
        sigma = np.where(valid, sigma, 0.0).astype(np.float32)
        targets = {}
        if per_zone > 1 or targets_per_zone is not None:
            targets = {"target_mean_m": mean, "target_sigma_m": sigma, "target_valid": valid,
                       "target_status": status, "target_order": target_order}
        return cls(mean_m=mean[..., 0], sigma_m=sigma[..., 0], valid=valid[..., 0],
                   status=status[..., 0], timestamp_s=timestamp_s, sensor_model=sensor_model,
                   **targets)


def number_array(values, name: str) -> np.ndarray:
    """Flat float64 array of a list (or array) of numbers, refusing anything else.

    Strings (``"1.5"``) and booleans are refused rather than converted: a file or driver
    that stores them is not what the reader expects, and converting hides that.

    Args:
        values: a (nested) list or tuple of int / float, or a numeric numpy array.
        name: what the values are, for the error message (e.g. ``"zones.json: mean_m"``).

    Raises:
        ValueError: ``"<name> must hold numbers, got ..."``.
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
    return np.asarray(flat, dtype=np.float64)


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
    codes = _numbers(values, name)
    bad = ~np.isfinite(codes) | (codes < 0) | (codes > 255) | (codes != np.round(codes))
    if np.any(bad):
        raise ValueError(f"{name} must hold integer codes in 0..255, got "
                         f"{codes[bad].reshape(-1)[0]:g}")
    return codes.astype(np.uint8)


def _numbers(values, name: str) -> np.ndarray:
    """An array of numbers (any shape), refusing strings, booleans and objects."""
    array = np.asarray(values)
    if array.dtype.kind not in "iuf":
        shown = "booleans" if array.dtype.kind == "b" else f"values of type {array.dtype}"
        raise ValueError(f"{name} must hold numbers, got {shown}")
    return array


def _flags(values, name: str) -> np.ndarray:
    """A bool array of booleans or 0/1 numbers, refusing strings and other numbers."""
    array = np.asarray(values)
    if array.dtype.kind != "b" and (array.dtype.kind not in "iuf"
                                    or not np.all(np.isin(array, (0, 1)))):
        raise ValueError(f"{name} must hold booleans (or 0/1), got values of type "
                         f"{array.dtype}" + ("" if array.dtype.kind not in "iuf" else
                                             " other than 0 and 1"))
    return array.astype(bool)


def _grid_from_count(count: int, name: str) -> int:
    n = math.isqrt(count)
    if n * n != count or n not in SUPPORTED_GRIDS:
        raise ValueError(f"{name} has {count} zones; expected 16 (4x4) or 64 (8x8)")
    return n
