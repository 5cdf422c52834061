"""What each zone reports for a plane, in closed form (the zone reading model).

A zone does not report the plane's depth at its centre ray, nor the mean depth over its
footprint: the sensor model (:mod:`deltar.sensor.simulate`) histograms the z-depths of
the footprint in 4 cm bins, subtracts a noise floor from every bin, keeps the strongest
run of bins and reports the count-weighted mean of the kept bins' centres. A plane
fitted to the readings as if each were the depth at some point of its cell
(:func:`deltar.calibration.plane.fit_plane_to_zones`) is therefore biased on planes seen
at an angle, in three ways: the depth ``z = -d / (n . ray)`` is convex across the
footprint, so the footprint's mean lies beyond the centre ray's depth, more so on the
far side, and the plane looks more tilted than it is (by 0.06-0.18 degrees 20-60
degrees off head-on); the bin centres quantise the mean; and the floor trims the
footprint's sparse tails unevenly (up to 0.6 degrees on single views beyond 50 degrees).

:class:`ZoneReadingModel` predicts the reading for any plane. The footprint is the
zone's cell in ``(tan ax, tan ay)`` (its z-depth samples are even there, as the sensor
model's pixels are), so the share of the footprint whose depth lies below ``e`` is the
share of the cell where the linear function ``w = n . (u, v, 1)`` lies below ``-d / e``:
the distribution of a sum of two uniform variables, a trapezoid whose cumulative
function is closed form. Each bin's count is that share times the footprint's sample
count; then the noise floor, the strongest run and the mean follow the sensor model
step for step. The prediction is continuous in the plane, so planes and the extrinsic
can be fitted to the readings by least squares (:func:`refit_zone_plane`,
:func:`refine_extrinsics_to_zones`). It matches the simulator's readings to about 1 mm
rms; what is left comes from the simulator's footprints being whole pixels, whose
edges sit up to 1.6 % of a zone away from the even angular split.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from deltar.calibration.plane import ZonePlaneFit, zone_cells_tan
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics
from deltar.sensor.simulator_config import SimulatorConfig

#: Footprint samples (pixels) per zone side of the sensor model
#: (:func:`deltar.calibration.synthetic.sensor_virtual_camera`): with the noise floor in
#: counts it sets which share of a zone's footprint a bin must hold to be kept.
PIXELS_PER_ZONE = 16


def _trapezoid_cdf(x: np.ndarray, narrow: np.ndarray, wide: np.ndarray) -> np.ndarray:
    """P(A + B <= x) for A uniform on [0, narrow] and B on [0, wide], narrow <= wide;
    piecewise, so that a width of 0 (a cell seen head-on along an axis) is exact."""
    a, b = np.broadcast_arrays(narrow, wide)
    ab = np.maximum(a * b, 1e-300)
    rise = x * x / (2 * ab)
    flat = (x - a / 2) / np.maximum(b, 1e-300)
    fall = 1.0 - (a + b - x) ** 2 / (2 * ab)
    out = np.where(x < a, rise, np.where(x < b, flat, fall))
    return np.where(x <= 0, 0.0, np.where(x >= a + b, 1.0, out))


@dataclass(frozen=True)
class ZoneReadingModel:
    """The sensor model's zone reading of a plane (see the module docstring).

    Attributes:
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) field of view in degrees, split evenly in angle.
        config: the histogram's bins, range, ignored bins and noise floor (counts).
        pixels_per_zone: footprint samples per zone side on average (the counts' scale).
    """

    grid: int = 8
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG
    config: SimulatorConfig = field(default_factory=SimulatorConfig)
    pixels_per_zone: float = PIXELS_PER_ZONE

    def __post_init__(self) -> None:
        if self.grid not in (4, 8):
            raise ValueError(f"ZoneReadingModel.grid must be 4 or 8, got {self.grid}")
        if not self.pixels_per_zone > 0:
            raise ValueError(f"ZoneReadingModel.pixels_per_zone must be > 0, got "
                             f"{self.pixels_per_zone}")

    def predict(self, normals: np.ndarray, offsets_m: np.ndarray | float,
                ) -> tuple[np.ndarray, np.ndarray]:
        """Each zone's reading of planes ``n . p + d = 0`` in the sensor frame.

        Args:
            normals: (3,) or (V, 3) unit normals oriented towards the sensor.
            offsets_m: () or (V,) offsets d in metres (> 0: the plane is in front).

        Returns:
            ``(mean_m, valid)``: (Z,) or (V, Z) float64 predicted zone means (z-depth,
            metres; 0 where invalid) and bool zones with counts left after the noise
            floor.
        """
        single = np.ndim(normals) == 1
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(offsets_m, dtype=np.float64).reshape(-1)
        if d.size != n.shape[0]:
            raise ValueError(f"offsets_m has {d.size} planes, normals has {n.shape[0]}")
        mean, valid = self._predict(n, d)
        return (mean[0], valid[0]) if single else (mean, valid)

    def _predict(self, n: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        cells = zone_cells_tan(self.grid, self.fov_deg)  # (v0, u0, v1, u1)
        v0, u0, v1, u1 = (c[None] for c in cells.T)  # (1, Z)
        nx, ny, nz, d = n[:, 0, None], n[:, 1, None], n[:, 2, None], d[:, None]
        # w = nx u + ny v + nz over the cell: uniform on width p plus uniform on width q.
        p, q = np.abs(nx) * (u1 - u0), np.abs(ny) * (v1 - v0)
        low = np.minimum(nx * u0, nx * u1) + np.minimum(ny * v0, ny * v1) + nz
        high = low + p + q
        narrow, wide = np.minimum(p, q), np.maximum(p, q)
        width = cfg.bin_width_m
        with np.errstate(divide="ignore", invalid="ignore"):
            near = np.where(low < 0, -d / low, np.inf)  # z = -d / w where w < 0
            far = np.where(high < 0, -d / high, np.inf)
        last = cfg.num_bins - 1
        first_bin = np.clip(np.floor(near / width), 0, last)
        last_bin = np.clip(np.floor(np.minimum(far, cfg.max_range_m) / width), 0, last)
        span = int(np.max(last_bin - first_bin)) + 1 if np.isfinite(near).any() else 1
        bins = first_bin[..., None] + np.arange(span)  # (V, Z, K)
        edges = np.stack([bins, bins + 1], axis=-1) * width  # (V, Z, K, 2)
        # Share of the cell with depth below each edge: P(w <= -d / e).
        with np.errstate(divide="ignore"):
            x = -d[..., None, None] / edges - low[..., None, None]
        share = _trapezoid_cdf(x, narrow[..., None, None], wide[..., None, None])
        size = self.grid * self.pixels_per_zone
        density = (size / 2 / np.tan(np.deg2rad(self.fov_deg[0] / 2))) * \
            (size / 2 / np.tan(np.deg2rad(self.fov_deg[1] / 2)))
        samples = density * (u1 - u0) * (v1 - v0)  # footprint samples per zone (1, Z)
        counts = samples[..., None] * (share[..., 1] - share[..., 0])
        counts = np.where((bins <= last_bin[..., None]) & (bins >= cfg.ignored_bins) &
                          np.isfinite(near)[..., None], counts, 0.0)
        counts = np.maximum(counts - cfg.noise_floor_counts, 0.0)
        kept = _strongest_run(counts)
        total = kept.sum(-1)
        valid = total > 0
        centres = (bins + 0.5) * width
        mean = (kept * centres).sum(-1) / np.where(valid, total, 1.0)
        return np.where(valid, mean, 0.0), valid


def _strongest_run(counts: np.ndarray) -> np.ndarray:
    """(..., K) counts zeroed outside the run of consecutive non-empty bins with the
    largest total (the first on ties), as :func:`deltar.sensor.simulate.strongest_cluster`."""
    nonzero = counts > 0
    previous = np.concatenate([np.zeros_like(nonzero[..., :1]), nonzero[..., :-1]], axis=-1)
    run_id = np.cumsum(nonzero & ~previous, axis=-1) * nonzero  # 0: empty bin
    flat_id = run_id.reshape(-1, counts.shape[-1])
    rows = np.repeat(np.arange(flat_id.shape[0]), counts.shape[-1])
    sums = np.zeros((flat_id.shape[0], counts.shape[-1] + 1))
    np.add.at(sums, (rows, flat_id.ravel()), counts.reshape(-1))
    sums[:, 0] = -1.0
    best = np.argmax(sums, axis=1).reshape(counts.shape[:-1])
    return np.where(run_id == best[..., None], counts, 0.0)


def _turn(normal: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The unit normal turned by about x[0], x[1] radians about two axes across it."""
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    turned = normal + x[0] * a + x[1] * np.cross(normal, a)
    return turned / np.linalg.norm(turned)


#: A refitted zone plane is kept only this close to the EM fit it starts from (degrees,
#: metres); farther means the readings do not follow the model (clutter, another surface).
MAX_REFIT_TURN_DEG = 5.0
MAX_REFIT_SHIFT_M = 0.05


def refit_zone_plane(fit: ZonePlaneFit, mean_m: np.ndarray,
                     model: ZoneReadingModel | None = None) -> ZonePlaneFit:
    """The plane whose predicted zone readings best match the measured ones.

    Least squares over the fit's inlier zones, starting from ``fit`` (the EM plane of
    :func:`deltar.calibration.plane.fit_plane_to_zones`, which treats each reading as a
    depth somewhere in its cell and so inherits the reading's bias on tilted planes).

    Args:
        fit: the EM fit of the same frame.
        mean_m: (Z,) the frame's zone means in metres (z-depth).
        model: the zone reading model (grid and field of view must be the frame's);
            default ``ZoneReadingModel()`` for the fit's grid.

    Returns:
        ``fit`` with the refitted normal and offset and ``rms_residual_m`` the RMS of
        measured minus predicted readings (metres); ``fit`` itself when the refit moves
        the plane more than ``MAX_REFIT_TURN_DEG`` / ``MAX_REFIT_SHIFT_M``.
    """
    from scipy.optimize import least_squares

    mean = np.asarray(mean_m, dtype=np.float64).reshape(-1)
    if mean.size != fit.inliers.size:
        raise ValueError(f"mean_m has {mean.size} zones, the fit has {fit.inliers.size}")
    if model is None:
        model = ZoneReadingModel(grid=math.isqrt(mean.size))
    use = fit.inliers
    measured = mean[use]

    def plane(x: np.ndarray) -> tuple[np.ndarray, float]:
        return _turn(fit.normal, x[:2]), fit.offset_m + x[2]

    def residuals(x: np.ndarray) -> np.ndarray:
        predicted, valid = model.predict(*plane(x))
        # A zone the model calls empty (rare, grazing) keeps its reading's own value.
        return np.where(valid[use], predicted[use], measured) - measured

    solution = least_squares(residuals, np.zeros(3), x_scale=np.full(3, 0.01),
                             diff_step=1e-6)
    normal, offset = plane(solution.x)
    turn = np.degrees(np.arccos(np.clip(normal @ fit.normal, -1.0, 1.0)))
    if turn > MAX_REFIT_TURN_DEG or abs(offset - fit.offset_m) > MAX_REFIT_SHIFT_M:
        return fit
    rms = float(np.sqrt(np.mean(solution.fun ** 2)))
    return replace(fit, normal=normal, offset_m=float(offset), rms_residual_m=rms)


@dataclass(frozen=True)
class ZoneRefinement:
    """Result of :func:`refine_extrinsics_to_zones`.

    Attributes:
        extrinsics: the refined sensor-to-camera transform.
        rms_residual_m: RMS of measured minus predicted zone readings, metres.
        zone_noise_m: the readings' robust spread at the start (sets the loss scale).
        zones: zone readings used.
        success: scipy's convergence flag.
    """

    extrinsics: SensorExtrinsics
    rms_residual_m: float
    zone_noise_m: float
    zones: int
    success: bool


def refine_extrinsics_to_zones(planes_cam: Sequence[tuple[np.ndarray, float]],
                               zone_means_m: Sequence[np.ndarray],
                               zone_masks: Sequence[np.ndarray], start: SensorExtrinsics,
                               model: ZoneReadingModel | None = None, *,
                               min_loss_scale_m: float = 0.01) -> ZoneRefinement:
    """The extrinsic whose predicted zone readings of the views' planes best match them.

    Each view's plane is known in the camera frame (e.g. the board's); for a candidate
    extrinsic it is moved into the sensor frame, each zone's reading predicted with
    ``model`` and compared with the measured one. All views are solved jointly (robust
    soft-L1 least squares over the rotation and translation). With the zones' noise the
    only error this is the maximum-likelihood extrinsic, which the closed form from
    per-view plane pairs is not (each zone plane's error is correlated across its
    normal and offset in a way a plane pair's weight does not carry).

    Args:
        planes_cam: per view ``(normal (3,), offset d in metres)`` in the camera frame,
            the normal towards the camera.
        zone_means_m: per view (Z,) measured zone means (z-depth, metres).
        zone_masks: per view (Z,) bool zones that see the plane.
        start: the starting sensor-to-camera transform (e.g. the plane-pair solution).
        model: the zone reading model (default ``ZoneReadingModel()`` for the zones' grid).
        min_loss_scale_m: the robust loss bends at twice the readings' robust spread,
            at least this (metres).

    Returns:
        ``ZoneRefinement``.

    Raises:
        ValueError: mismatched lengths or no zones.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    if not len(planes_cam) == len(zone_means_m) == len(zone_masks):
        raise ValueError(f"planes_cam, zone_means_m and zone_masks must have one entry per "
                         f"view, got {len(planes_cam)}, {len(zone_means_m)}, "
                         f"{len(zone_masks)}")
    normals = np.array([np.asarray(n, dtype=np.float64) for n, _ in planes_cam]).reshape(-1, 3)
    offsets = np.array([float(d) for _, d in planes_cam])
    means = np.array([np.asarray(m, dtype=np.float64).reshape(-1) for m in zone_means_m])
    masks = np.array([np.asarray(m, dtype=bool).reshape(-1) for m in zone_masks])
    if not masks.any():
        raise ValueError("no zone readings to refine the extrinsic against")
    if model is None:
        model = ZoneReadingModel(grid=math.isqrt(means.shape[1]))
    measured = means[masks]

    def transform(x: np.ndarray) -> SensorExtrinsics:
        return SensorExtrinsics(Rotation.from_rotvec(x[:3]).as_matrix() @ start.rotation,
                                start.translation_m + x[3:])

    def residuals(x: np.ndarray) -> np.ndarray:
        ext = transform(x)
        predicted, valid = model.predict(normals @ ext.rotation,
                                         offsets + normals @ ext.translation_m)
        return np.where(valid[masks], predicted[masks], measured) - measured

    initial = residuals(np.zeros(6))
    noise = float(1.4826 * np.median(np.abs(initial - np.median(initial))))
    solution = least_squares(residuals, np.zeros(6), loss="soft_l1",
                             f_scale=max(2.0 * noise, min_loss_scale_m),
                             x_scale=np.full(6, 1e-3), diff_step=1e-6)
    return ZoneRefinement(transform(solution.x), float(np.sqrt(np.mean(solution.fun ** 2))),
                          noise, int(measured.size), bool(solution.success))
