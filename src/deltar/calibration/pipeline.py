"""End-to-end sensor-camera calibration of a recording (what ``deltar calibrate`` runs)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from deltar.calibration.extrinsic import (
    PlaneObservation,
    depth_to_points,
    mean_zone_to_cloud_distance,
    observation_from_points,
    solve_extrinsics,
)
from deltar.calibration.plane import ZonePlaneFit, fit_plane_to_zones
from deltar.calibration.rig import RigCalibration
from deltar.calibration.slam import Trajectory, world_to_camera
from deltar.calibration.zone_model import ZoneReadingModel, refit_zone_plane
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame


@dataclass
class CalibrationResult:
    """What a calibration run produced.

    Attributes:
        calibration: the rig calibration (save it with ``calibration.save(path)``).
        nominal: the starting guess.
        observations: the plane frames used.
        distance_before_m: mean zone-to-cloud distance with the nominal extrinsics.
        distance_after_m: the same with the calibrated extrinsics.
        skipped: (frame name, reason) of frames that could not be used.
        unpaired: zone frames left out because no colour/depth image lies within the
            pairing tolerance (depth-image calibration only).
    """

    calibration: RigCalibration
    nominal: SensorExtrinsics
    observations: list[PlaneObservation]
    distance_before_m: float
    distance_after_m: float
    skipped: list[tuple[str, str]] = field(default_factory=list)
    unpaired: int = 0


def zone_plane_from_frame(frame: ZoneFrame, *,
                          fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                          min_zone_fraction: float = 0.6, max_incidence_deg: float = 60.0,
                          zone_model: bool = False, name: str = "") -> ZonePlaneFit:
    """The frame's plane in the sensor frame, refused when one plane does not fill the view.

    The EM fit (:func:`~deltar.calibration.plane.fit_plane_to_zones`) finds the plane and
    its zones; with ``zone_model`` the plane is then refitted so that the zone readings it
    predicts (:func:`deltar.calibration.zone_model.refit_zone_plane`) match the measured
    ones, which removes the readings' bias on tilted planes. That model assumes a flat
    surface filling each zone (the board path's wall); on real rooms, where surfaces
    are not quite flat and zones mix surfaces, the EM plane's slack (each reading may lie
    anywhere in its cell) does better, so it is off by default.

    Args:
        frame: the zone frame (means are z-depth in metres).
        fov_deg: sensor field of view in degrees.
        min_zone_fraction: fewest valid zones (fraction) that must lie on the plane.
        max_incidence_deg: largest angle between the plane's normal and the sensor's
            axis; grazing planes are fitted poorly from zones.
        zone_model: refit the plane to the zone reading model (flat surfaces only).
        name: label for error messages.

    Raises:
        ValueError: the frame has no usable plane (the message says why).
    """
    try:
        plane = fit_plane_to_zones(frame, fov_deg=fov_deg)
    except ValueError as err:
        raise ValueError(f"frame {name}: {err}") from err
    incidence = float(np.degrees(np.arccos(min(1.0, abs(plane.normal[2])))))
    if incidence > max_incidence_deg:
        raise ValueError(f"frame {name}: the plane is seen {incidence:.0f} deg off head-on "
                         f"(at most {max_incidence_deg:.0f}): view planes more squarely")
    _, _, valid = frame.flat()
    fraction = plane.inliers.sum() / max(int(valid.sum()), 1)
    if fraction < min_zone_fraction:
        raise ValueError(f"frame {name}: only {fraction:.0%} of the valid zones lie on one "
                         f"plane (need {min_zone_fraction:.0%}): fill the sensor's view with "
                         "a flat surface")
    if zone_model:
        model = ZoneReadingModel(grid=frame.grid, fov_deg=tuple(fov_deg))
        plane = refit_zone_plane(plane, frame.flat()[0], model)
    return plane


def observation_from_frame(frame: ZoneFrame, cloud_cam_m: np.ndarray,
                           nominal: SensorExtrinsics, *,
                           fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                           visible_only: bool = False, min_zone_fraction: float = 0.6,
                           min_point_fraction: float = 0.5,
                           max_incidence_deg: float = 60.0, name: str = "") -> PlaneObservation:
    """Fit the frame's plane (sensor frame) and find it in the camera-frame cloud.

    Calibration needs frames where one plane fills most of the sensor's view; frames
    where it does not (clutter, corners) are refused rather than allowed to bias the fit.

    Args:
        frame: the zone frame (means are z-depth in metres).
        cloud_cam_m: (N, 3) scene points in the camera frame, metres.
        nominal: nominal sensor-to-camera transform.
        fov_deg: sensor field of view in degrees.
        visible_only: drop occluded cloud points (SLAM maps).
        min_zone_fraction: fewest valid zones (fraction) that must lie on the plane.
        min_point_fraction: fewest cloud points in the sensor's view (fraction) that must
            lie on the matching plane.
        max_incidence_deg: largest angle between the plane's normal and the sensor's
            axis; grazing planes are fitted poorly from zones.
        name: label for error messages.

    Raises:
        ValueError: the frame has no usable plane (the message says why).
    """
    plane = zone_plane_from_frame(frame, fov_deg=fov_deg, min_zone_fraction=min_zone_fraction,
                                  max_incidence_deg=max_incidence_deg, name=name)
    return observation_from_points(plane, frame.flat()[0], cloud_cam_m, nominal,
                                   fov_deg=fov_deg, visible_only=visible_only,
                                   min_point_fraction=min_point_fraction, name=name)


def calibrate_observations(
    observations: Sequence[PlaneObservation],
    nominal: SensorExtrinsics,
    intrinsics: CameraIntrinsics,
    *,
    grid: int = 8,
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
    sensor_model: str = "VL53L5CX",
    skipped: Sequence[tuple[str, str]] = (),
    start: SensorExtrinsics | None = None,
) -> CalibrationResult:
    """Solve the extrinsics from plane observations and package the result.

    The robust refinement starts from ``start`` (e.g. a closed-form solution) when
    given, else from ``nominal``; the "before" distance is always the nominal's.

    Raises:
        ValueError: too few or degenerate planes (the message says what to record).
    """
    solved = solve_extrinsics(observations, nominal if start is None else start)
    if solved.rejected:
        rejected = set(solved.rejected)
        skipped = [*skipped, *((name, "its plane disagrees with the other frames")
                               for name in solved.rejected)]
        observations = [o for o in observations if o.name not in rejected]
    before = mean_zone_to_cloud_distance(observations, nominal)
    after = mean_zone_to_cloud_distance(observations, solved.extrinsics)
    residuals = {"zone_to_cloud_before_m": before, "zone_to_cloud_after_m": after,
                 "point_to_plane_rms_m": solved.rms_point_to_plane_m,
                 "frames_used": float(len(observations))}
    calibration = RigCalibration(intrinsics=intrinsics, extrinsics=solved.extrinsics,
                                 grid=grid, fov_deg=fov_deg, sensor_model=sensor_model,
                                 residuals=residuals)
    return CalibrationResult(calibration, nominal, list(observations), before, after,
                             list(skipped))


def calibrate_recording(
    recording,
    nominal: SensorExtrinsics,
    *,
    tolerance_s: float = 0.02,
    fov_deg: tuple[float, float] | None = None,
    trajectory: Trajectory | None = None,
    slam_points_world: np.ndarray | None = None,
    depth_stride: int = 4,
    time_offset_s: float = 0.0,
) -> CalibrationResult:
    """Calibrate from a ``deltar.io.recording.Recording``.

    Camera-frame points come from the recording's depth images, or, when
    ``trajectory`` and ``slam_points_world`` are given, from the SLAM map seen from the
    camera pose at each zone frame's time.

    Args:
        recording: the recording (``Recording``).
        nominal: nominal sensor-to-camera transform.
        tolerance_s: pairing tolerance between zone frames and images, seconds.
        fov_deg: sensor field of view in degrees (default: the recording's).
        trajectory: camera-to-world poses (SLAM), optional.
        slam_points_world: (N, 3) SLAM map in the world frame, with ``trajectory``.
        depth_stride: use every n-th depth pixel per row and column.
        time_offset_s: camera clock minus sensor clock (seconds), applied when pairing
            (and to the SLAM trajectory's times); stored in the calibration.

    Returns:
        ``CalibrationResult``; frames without a usable plane are listed in ``skipped``,
        zone frames without an image nearby are counted in ``unpaired``.

    Raises:
        ValueError: no zone frame has a depth image (and no SLAM map is given), too few
            usable or too similar planes (the message says what to record).
    """
    use_slam = trajectory is not None
    if use_slam != (slam_points_world is not None):
        raise ValueError("give both the SLAM point cloud and the trajectory, or neither")
    meta = recording.meta
    fov = tuple(fov_deg) if fov_deg is not None else tuple(meta.fov_deg)
    if len(fov) != 2 or not all(np.isfinite(v) and 0 < v < 180 for v in fov):
        raise ValueError(f"sensor field of view must be two angles in (0, 180) degrees, got "
                         f"{fov}")
    observations, skipped = [], []
    unpaired = 0
    if use_slam:
        items = [(f, None) for f in recording.zone_frames()]
    else:
        items = [(p.zone_frame, p) for p in recording.pairs(tolerance_s, time_offset_s)]
        if not items:  # not the planes' fault: say what did not pair
            from deltar.io.recording import no_pairs_message

            raise ValueError(no_pairs_message(recording, tolerance_s, time_offset_s))
        unpaired = len(recording.zone_frames()) - len(items)
        if items and all(pair.depth_path is None for _, pair in items):
            raise ValueError(f"{recording.folder}: no depth image within {tolerance_s} s of "
                             "any zone frame (is depth/ missing or empty?): calibration needs "
                             "depth images, or a SLAM map and trajectory")
    for frame, pair in items:
        name = f"t={frame.timestamp_s:.3f}s"
        try:
            if use_slam:
                pose = trajectory.pose_at(frame.timestamp_s + time_offset_s,
                                          max_gap_s=max(tolerance_s, 0.1))
                if pose is None:
                    raise ValueError(f"frame {name}: no camera pose near this time")
                cloud = world_to_camera(slam_points_world, pose)
            else:
                if pair.depth_path is None:
                    raise ValueError(f"frame {name}: no depth image within {tolerance_s} s")
                cloud = depth_to_points(pair.load_depth(), meta.intrinsics, depth_stride)
            observations.append(observation_from_frame(
                frame, cloud, nominal, fov_deg=fov, visible_only=use_slam, name=name))
        except ValueError as err:
            skipped.append((name, str(err)))
    if skipped:
        warnings.warn(f"{len(skipped)} of {len(items)} frames had no usable plane; first: "
                      f"{skipped[0][1]}", stacklevel=2)
    try:
        result = calibrate_observations(observations, nominal, meta.intrinsics,
                                        grid=meta.grid, fov_deg=fov,
                                        sensor_model=meta.sensor_model, skipped=skipped)
    except ValueError as err:
        if not skipped:
            raise
        # Too few planes: why the others were skipped is what the user needs to know.
        name, reason = skipped[0]
        first = reason if str(name) in reason else f"{name}: {reason}"
        raise ValueError(f"{err} ({len(skipped)} of {len(items)} frames were skipped; the "
                         f"first: {first})") from err
    result.unpaired = unpaired
    if time_offset_s:
        result.calibration = replace(result.calibration, time_offset_s=float(time_offset_s))
    return result


def other_roll_guesses(roll_deg: float) -> list[float]:
    """The other quarter-turn rolls to try when a nominal roll guess fails, degrees.

    A sensor is usually mounted in one of four quarter-turn orientations; a wrong one
    (e.g. -90 instead of 90) can leave too few frames consistent with each other.

    Returns:
        ``roll_deg + 90``, ``+ 180`` and ``+ 270``, wrapped to (-180, 180].
    """
    out = []
    for step in (90.0, 180.0, 270.0):
        value = (roll_deg + step) % 360.0
        out.append(value - 360.0 if value > 180.0 else value)
    return out
