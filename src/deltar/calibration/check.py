"""Score a rig calibration on a recording: per-zone residuals against a reference surface.

For each zone frame paired with an image, every valid zone's measured mean is compared
with the z-depth the calibration predicts for that zone from the camera's side: the
board's plane (a printed board fixed on a flat surface, as for ``deltar calibrate
--target``) or the recording's depth image. A calibration that still fits leaves
residuals at the zones' noise (1-2 cm) with no pattern across the grid; a bumped rig
shows a bias or a tilt across the zone map.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deltar.calibration.board import BoardDetector, BoardSpec, estimate_board_pose
from deltar.calibration.plane import zone_cells_tan
from deltar.calibration.rig import RigCalibration, pairing_time_offset
from deltar.camera import backproject
from deltar.io.atomic import atomic_path
from deltar.sensor.geometry import DEFAULT_FOV_DEG

#: A zone farther than this from the reference (metres) sees another surface: it is
#: counted as off the surface and left out of the statistics.
OFF_SURFACE_M = 0.10
#: Verdict thresholds: median |residual| and |median residual| (metres).
FIT_MEDIAN_ABS_M = 0.025
FIT_BIAS_M = 0.015
#: Verdict threshold on the tilt between the measured and the predicted surface across
#: the zone map (degrees, rms over frames, the zones' noise removed): a turned
#: extrinsic tilts every view's residuals, which the median and bias can miss (they
#: passed a calibration 5 deg off in pitch or 20 deg in roll).
FIT_TILT_DEG = 3.0


@dataclass(frozen=True)
class CalibrationCheck:
    """Per-zone residuals of a calibration on a recording.

    Attributes:
        residuals_m: (F, Z) measured minus predicted zone mean, metres; NaN where the zone
            is invalid or has no reference.
        frame_names: (F,) labels of the frames scored.
        reference: ``"board"`` or ``"depth"``.
        grid: zones per side.
        skipped: frames without a reference (no board found, no depth image).
        predicted_m: (F, Z) the predicted zone means, metres (NaN: no reference); None
            leaves the tilt out of the verdict.
        fov_deg: the sensor's field of view (degrees), for the zones' directions.
    """

    residuals_m: np.ndarray
    frame_names: tuple[str, ...]
    reference: str
    grid: int
    skipped: int = 0
    predicted_m: np.ndarray | None = None
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG

    @property
    def on_surface(self) -> np.ndarray:
        """(F, Z) bool: zones with a reference within ``OFF_SURFACE_M``."""
        return np.isfinite(self.residuals_m) & (np.abs(np.nan_to_num(self.residuals_m))
                                                <= OFF_SURFACE_M)

    def _kept(self) -> np.ndarray:
        return self.residuals_m[self.on_surface]

    @property
    def median_abs_m(self) -> float:
        """Median |residual| of the zones on the surface, metres."""
        return float(np.median(np.abs(self._kept())))

    @property
    def bias_m(self) -> float:
        """Median residual of the zones on the surface, metres (> 0: zones read farther)."""
        return float(np.median(self._kept()))

    @property
    def rms_m(self) -> float:
        """RMS residual of the zones on the surface, metres."""
        return float(np.sqrt(np.mean(self._kept() ** 2)))

    @property
    def off_surface_fraction(self) -> float:
        """Fraction of zones with a reference that are off the surface."""
        scored = np.isfinite(self.residuals_m)
        return float(1.0 - self.on_surface.sum() / max(int(scored.sum()), 1))

    def zone_median_m(self) -> np.ndarray:
        """(grid, grid) median residual per zone over the frames (NaN: never scored)."""
        values = np.where(self.on_surface, self.residuals_m, np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN zones
            return np.nanmedian(values, axis=0).reshape(self.grid, self.grid)

    @property
    def tilt_rms_deg(self) -> float:
        """RMS over frames of the tilt between the measured and the predicted surface
        (the per-frame linear trend of the residuals across the zone map over the
        predicted depth, its noise-expected part taken off), degrees; 0 with too few
        zones or no ``predicted_m``."""
        if self.predicted_m is None:
            return 0.0
        cells = zone_cells_tan(self.grid, self.fov_deg)
        uv = np.column_stack([(cells[:, 1] + cells[:, 3]) / 2, (cells[:, 0] + cells[:, 2]) / 2])
        excess = []
        for res, pred, keep in zip(self.residuals_m, self.predicted_m, self.on_surface,
                                   strict=True):
            if keep.sum() < 6:
                continue
            design = np.column_stack([np.ones(int(keep.sum())), uv[keep]])
            coef, *_ = np.linalg.lstsq(design, res[keep], rcond=None)
            dof = int(keep.sum()) - 3
            noise = float(np.sum((res[keep] - design @ coef) ** 2)) / dof
            cov = noise * np.linalg.inv(design.T @ design)
            depth = float(np.mean(pred[keep]))
            excess.append((coef[1] ** 2 + coef[2] ** 2 - cov[1, 1] - cov[2, 2]) / depth ** 2)
        if not excess:
            return 0.0
        return float(np.degrees(np.arctan(np.sqrt(max(0.0, float(np.mean(excess)))))))

    @property
    def fits(self) -> bool:
        """Whether the residuals look like zone noise (see the module's thresholds)."""
        return (self.median_abs_m <= FIT_MEDIAN_ABS_M and abs(self.bias_m) <= FIT_BIAS_M
                and self.tilt_rms_deg <= FIT_TILT_DEG)


def _cell_samples(grid: int, fov_deg, per_side: int = 4) -> np.ndarray:
    """(Z, S, 2) (u, v) = (tan ax, tan ay) samples spread evenly over each zone's cell."""
    cells = zone_cells_tan(grid, fov_deg)  # (v0, u0, v1, u1)
    t = (np.arange(per_side) + 0.5) / per_side
    fu, fv = np.meshgrid(t, t)
    u = cells[:, 1, None] + (cells[:, 3] - cells[:, 1])[:, None] * fu.ravel()
    v = cells[:, 0, None] + (cells[:, 2] - cells[:, 0])[:, None] * fv.ravel()
    return np.stack([u, v], axis=-1)


def predicted_from_plane(normal_cam: np.ndarray, offset_cam_m: float,
                         calibration: RigCalibration) -> np.ndarray:
    """(Z,) zone means (z-depth, metres) the sensor would read of a camera-frame plane.

    The plane (``n . p + d = 0``) is mapped into the sensor frame with the calibration's
    extrinsics and its z-depth averaged over each zone's cell; NaN where it is behind.
    """
    ext = calibration.extrinsics
    normal = ext.rotation.T @ np.asarray(normal_cam, dtype=np.float64)
    offset = float(offset_cam_m) + float(np.asarray(normal_cam) @ ext.translation_m)
    uv = _cell_samples(calibration.grid, calibration.fov_deg)
    denom = normal[0] * uv[..., 0] + normal[1] * uv[..., 1] + normal[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -offset / denom
    z = np.where(z > 0, z, np.nan)
    return z.mean(axis=1)


def predicted_from_points(points_cam_m: np.ndarray, calibration: RigCalibration,
                          min_points: int = 5) -> np.ndarray:
    """(Z,) mean z-depth (metres, sensor frame) of the camera points inside each zone's
    cell; NaN for cells with fewer than ``min_points`` points."""
    ext = calibration.extrinsics
    sensor = (np.asarray(points_cam_m, dtype=np.float64) - ext.translation_m) @ ext.rotation
    sensor = sensor[sensor[:, 2] > 1e-6]
    u, v = sensor[:, 0] / sensor[:, 2], sensor[:, 1] / sensor[:, 2]
    cells = zone_cells_tan(calibration.grid, calibration.fov_deg)
    out = np.full(len(cells), np.nan)
    for k, (v0, u0, v1, u1) in enumerate(cells):
        inside = (u >= u0) & (u < u1) & (v >= v0) & (v < v1)
        if inside.sum() >= min_points:
            out[k] = float(sensor[inside, 2].mean())
    return out


#: Fewest frames scored for a verdict on a calibration.
MIN_CHECK_FRAMES = 3


def check_calibration(recording, calibration: RigCalibration, *, spec: BoardSpec | None = None,
                      tolerance_s: float = 0.02, time_offset_s: float | None = None,
                      depth_stride: int = 2,
                      calibration_name: str = "the calibration") -> CalibrationCheck:
    """Score ``calibration`` on a recording (board plane with ``spec``, else depth images).

    Args:
        recording: a ``deltar.io.recording.Recording``.
        calibration: the rig calibration to score.
        spec: the board the recording shows; None to use the depth images.
        tolerance_s: pairing tolerance, seconds.
        time_offset_s: camera minus sensor clock, seconds (default: the calibration's).
        depth_stride: every n-th depth pixel per row and column.
        calibration_name: how messages name the calibration (e.g. ``--calib c.json``).

    Raises:
        ValueError: the calibration is for another resolution or grid, or fewer than
            :data:`MIN_CHECK_FRAMES` frames have a reference (the message says which one
            was missing).
    """
    meta = recording.meta
    intr = calibration.intrinsics
    calibration.check_image_size((meta.intrinsics.height, meta.intrinsics.width),
                                 f"the recording {recording.folder}", calibration_name)
    if calibration.grid != meta.grid:
        raise ValueError(f"{calibration_name} is for a {calibration.grid}x{calibration.grid} "
                         f"grid, the recording {recording.folder} has {meta.grid}x{meta.grid}")
    offset = pairing_time_offset(calibration, time_offset_s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pairs = recording.pairs(tolerance_s, time_offset_s=offset)
    detector = BoardDetector(spec) if spec is not None else None
    rows, predictions, names, skipped = [], [], [], 0
    for pair in pairs:
        frame = pair.zone_frame
        if detector is not None:
            detection = detector.detect(pair.load_color())
            if detection is None:
                skipped += 1
                continue
            pose = estimate_board_pose(detection, intr, calibration.distortion)
            predicted = predicted_from_plane(pose.normal_cam, pose.offset_cam_m, calibration)
        else:
            if pair.depth_path is None:
                skipped += 1
                continue
            points = backproject(pair.load_depth(), intr, stride=depth_stride)
            predicted = predicted_from_points(points, calibration)
        mean, _, valid = frame.flat()
        rows.append(np.where(valid, mean - predicted, np.nan))
        predictions.append(predicted)
        names.append(f"t={frame.timestamp_s:.3f}s")
    if not rows:
        what = "the board is found in no paired image" if spec is not None else \
            "no zone frame has a depth image (pass --target for a board recording)"
        if not pairs:  # nothing paired: the board or depth was never looked for
            source = (f"{calibration_name}'s" if time_offset_s is None
                      else "the time offset given")
            what = (f"no zone frame pairs with an image within {tolerance_s:g} s at "
                    f"{source} time offset of {offset:+g} s")
        raise ValueError(f"{recording.folder}: nothing to score against: {what}")
    if len(rows) < MIN_CHECK_FRAMES:  # one view is no verdict on a rig
        what = "the board is found" if spec is not None else "zone frames have a depth image"
        raise ValueError(f"{recording.folder}: {what} in only {len(rows)} of {len(pairs)} "
                         f"paired frames; a verdict needs at least {MIN_CHECK_FRAMES} (check "
                         "--target, or record more)")
    residuals = np.stack(rows)
    if not np.isfinite(residuals).any():
        raise ValueError(f"{recording.folder}: no valid zone has a reference")
    result = CalibrationCheck(residuals, tuple(names), "board" if spec is not None else "depth",
                              calibration.grid, skipped, np.stack(predictions),
                              tuple(calibration.fov_deg))
    if not result.on_surface.any():
        raise ValueError(f"{recording.folder}: every zone is more than "
                         f"{100 * OFF_SURFACE_M:.0f} cm from the reference surface: the "
                         "calibration does not fit this rig at all (or the wrong --target)")
    return result


def plot_check(path: str | os.PathLike, check: CalibrationCheck, *, title: str = "",
               overwrite: bool = False) -> Path:
    """Picture of a check: the per-zone median residual map and the residual histogram (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    zone_map = 100 * check.zone_median_m()
    limit = max(2.0, float(np.nanmax(np.abs(zone_map))) if np.isfinite(zone_map).any() else 2.0)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    shown = axes[0].imshow(zone_map, cmap="coolwarm", vmin=-limit, vmax=limit)
    for (r, c), value in np.ndenumerate(zone_map):
        if np.isfinite(value):
            axes[0].text(c, r, f"{value:.1f}", ha="center", va="center", fontsize=6)
    axes[0].set_title("median residual per zone (cm, + = zone reads farther)")
    axes[0].set_xticks([])
    axes[0].set_yticks([])
    fig.colorbar(shown, ax=axes[0], fraction=0.046)
    kept = 100 * check.residuals_m[check.on_surface]
    axes[1].hist(kept, bins=40, color="steelblue")
    axes[1].axvline(0, color="black", linewidth=0.8)
    axes[1].set_xlabel("zone residual (cm)")
    axes[1].set_ylabel("zones")
    axes[1].set_title(f"{len(check.frame_names)} frames: median |r| "
                      f"{100 * check.median_abs_m:.2f} cm, bias {100 * check.bias_m:+.2f} cm")
    fig.suptitle(title or f"calibration check against the {check.reference} "
                 f"({'fits' if check.fits else 'does not fit'})")
    fig.tight_layout()
    with atomic_path(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    return Path(path)
