"""Sensor-camera calibration with a printed board and no depth camera.

The board is fixed flat on a wall, a door or a table, so the surface the zones see is
the board's plane. Per colour image OpenCV finds the board and its pose, which gives
the plane in the camera frame; per zone frame the existing plane fit
(:func:`deltar.calibration.pipeline.zone_plane_from_frame`), refitted to the zone
reading model (:mod:`deltar.calibration.zone_model`), gives it in the sensor frame.
Plane pairs give the extrinsic in closed form (normals: Kabsch; offsets: linear least
squares), the existing robust point-to-plane refinement
(:func:`deltar.calibration.pipeline.calibrate_observations`) takes it further and drops
views that disagree, so the output file and report are those of the depth-image path;
last, the extrinsic is refined against the zone readings themselves, each view's board
plane predicting every zone's reading through the zone reading model (the
maximum-likelihood solution when the zones' noise dominates). The result also carries its
expected error (:mod:`deltar.calibration.board_uncertainty`): with 2 cm zone noise the
zones, not the board poses, limit the accuracy, and the roll about the viewing axis most
(it is seen only through the direction each view is tilted), so too few or too shallow
views are warned about.

Everything that would make the answer meaningless is refused before the refinement
(and before camera calibration): too few views with the board, a board spec whose
scale contradicts the zones, views where the zones miss the board's surface, plane
orientations that do not vary enough.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from deltar.calibration.board import (
    BoardDetection,
    BoardDetector,
    BoardPose,
    BoardSpec,
    board_points_in_view,
    estimate_board_pose,
)
from deltar.calibration.board_camera import (
    CameraCalibration,
    board_plane_sensitivity,
    calibrate_camera,
)
from deltar.calibration.board_scale import warn_board_scale
from deltar.calibration.board_uncertainty import ExtrinsicUncertainty, extrinsic_uncertainty
from deltar.calibration.extrinsic import (
    PlaneObservation,
    check_plane_diversity,
    closed_form_extrinsics,
    mean_zone_to_cloud_distance,
    normal_spread_deg,
    point_to_plane_rms,
)
from deltar.calibration.pipeline import (
    CalibrationResult,
    calibrate_observations,
    zone_plane_from_frame,
)
from deltar.calibration.plane import ZonePlaneFit, zone_centre_points
from deltar.calibration.time_offset import TimeOffsetEstimate, estimate_time_offset
from deltar.calibration.zone_model import ZoneReadingModel, refine_extrinsics_to_zones
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import SensorExtrinsics

#: Fewest views with the board found (and a usable zone plane) for the extrinsic.
MIN_BOARD_VIEWS = 6
#: Fewest views with the board for ``calibrate_intrinsics``.
MIN_INTRINSIC_VIEWS = 10
#: Allowed ratio between the board's distance from the camera and the zones' distance
#: to the same surface; outside it the board's printed size is not the spec's.
MAX_SCALE_RATIO = 1.25
#: A view's planes agree when the normals (mapped by the closed-form rotation) are within
#: this many degrees and the offsets within ``PLANE_AGREE_M``.
PLANE_AGREE_DEG = 8.0
PLANE_AGREE_M = 0.06
#: Expected errors (1 sd, from the zones' noise) above which the result comes with a
#: warning to record more views: about 1 in 10 calibrations from such views would miss
#: 0.5 deg or 10 mm (benchmarks/RESULTS.md, 2026-12-03).
MAX_EXPECTED_ROTATION_DEG = 0.35
MAX_EXPECTED_TRANSLATION_M = 0.005
#: Distances (metres) at which an A4 board fills most of a typical camera's image: views
#: from there pin the principal point down when the intrinsics are calibrated.
NEAR_VIEW_M = (0.3, 0.45)


@dataclass
class BoardReport:
    """What the board path adds to :class:`CalibrationResult`.

    Attributes:
        images_searched: colour images the board was looked for in.
        views_with_board: of those, images where it was found.
        pose_rms_px: median corner reprojection error of the board poses, pixels.
        time_offset: the estimate when ``time_offset_s="auto"``, else None.
        time_offset_s: the offset used for pairing, seconds.
        intrinsics_rms_px: RMS reprojection error of ``cv2.calibrateCamera`` (None when
            the intrinsics were not calibrated).
        closed_form: the closed-form extrinsic the refinement started from.
        uncertainty: the error the zones' noise leaves in the extrinsic (1 sd, the
            Cramer-Rao bound of :mod:`deltar.calibration.board_uncertainty`), with the
            calibrated intrinsics' error when they were calibrated.
        camera: the intrinsics' calibration with its covariance (None when the
            intrinsics were not calibrated).
    """

    images_searched: int
    views_with_board: int
    pose_rms_px: float
    time_offset: TimeOffsetEstimate | None
    time_offset_s: float
    intrinsics_rms_px: float | None = None
    closed_form: SensorExtrinsics | None = None
    skipped: list[tuple[str, str]] = field(default_factory=list)
    uncertainty: ExtrinsicUncertainty | None = None
    camera: CameraCalibration | None = None


@dataclass
class _View:
    """One zone frame paired with an image where the board was found."""

    name: str
    plane: ZonePlaneFit | None
    pose: BoardPose
    detection: BoardDetection
    mean_m: np.ndarray
    reason: str = ""

    def variances(self) -> tuple[float, float]:
        """(normal direction in rad^2, offset in m^2) variances of the two planes' pair."""
        n_zone, d_zone = _zone_plane_variances(self.plane)
        return (n_zone + self.pose.normal_std_rad ** 2, d_zone + self.pose.offset_std_m ** 2)


def _zone_plane_variances(plane: ZonePlaneFit, floor_m: float = 0.005) -> tuple[float, float]:
    """Approximate variances of a zone plane's normal direction (rad^2) and offset (m^2)
    from the scatter of its inlier points and their residual (at least ``floor_m``)."""
    points = plane.points_m[plane.inliers]
    centre = points.mean(axis=0)
    spread = np.sort(np.linalg.eigvalsh((points - centre).T @ (points - centre)))
    sigma2 = max(plane.rms_residual_m, floor_m) ** 2
    normal_var = sigma2 * (1.0 / max(spread[2], 1e-9) + 1.0 / max(spread[1], 1e-9))
    lateral = centre - (centre @ plane.normal) * plane.normal
    return normal_var, sigma2 / len(points) + float(lateral @ lateral) * normal_var / 2


def _agreeing(views: list[_View], offsets: bool = True
              ) -> tuple[SensorExtrinsics | None, np.ndarray]:
    """Closed-form extrinsic over the views whose two planes agree with it (trimmed).

    With ``offsets`` False only the normals must agree (a board spec of the wrong scale
    scales every camera offset but leaves the normals alone).

    Returns:
        The extrinsic (None with fewer than 3 views) and the (V,) bool mask of views
        that agree with it.
    """
    keep = np.ones(len(views), dtype=bool)
    if len(views) < 3:
        return None, np.zeros(len(views), dtype=bool)
    ns = np.array([v.plane.normal for v in views])
    ds = np.array([v.plane.offset_m for v in views])
    nc = np.array([v.pose.normal_cam for v in views])
    dc = np.array([v.pose.offset_cam_m for v in views])
    var = np.array([v.variances() for v in views])
    ext = None
    for _ in range(len(views)):
        if keep.sum() < 3:
            return ext, keep
        ext = closed_form_extrinsics(ns[keep], ds[keep], nc[keep], dc[keep],
                                     1 / var[keep, 0], 1 / var[keep, 1])
        angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", ns @ ext.rotation.T, nc),
                                             -1, 1)))
        offset = np.abs(ds - dc - nc @ ext.translation_m)
        if not offsets:
            offset = np.zeros_like(offset)
        bad = ((angle > PLANE_AGREE_DEG) | (offset > PLANE_AGREE_M)) & keep
        if not bad.any():
            return ext, keep
        # Drop the worst view and solve again (one outlier at a time: a bad view pulls
        # the solution towards itself and can make good views look bad).
        score = np.where(keep, angle / PLANE_AGREE_DEG + offset / PLANE_AGREE_M, -np.inf)
        keep[int(np.argmax(score))] = False
    return ext, keep


def calibrate_recording_with_board(
    recording,
    spec: BoardSpec,
    nominal: SensorExtrinsics,
    *,
    tolerance_s: float = 0.02,
    time_offset_s: float | str = 0.0,
    fov_deg: tuple[float, float] | None = None,
    intrinsics: CameraIntrinsics | None = None,
    distortion: tuple[float, ...] = (),
    calibrate_intrinsics: bool = False,
    max_offset_s: float = 0.5,
) -> tuple[CalibrationResult, BoardReport]:
    """Calibrate from a recording of colour images and zone frames of a board on a surface.

    Args:
        recording: a ``deltar.io.recording.Recording`` (its depth images are not used).
        spec: the printed board.
        nominal: the user's rough guess (the "before" of the report; the solution itself
            comes from the closed form).
        tolerance_s: pairing tolerance between a zone frame and an image, seconds.
        time_offset_s: camera-minus-sensor clock offset in seconds, or ``"auto"`` to
            estimate it from the board's distance over time.
        fov_deg: sensor field of view in degrees (default: the recording's).
        intrinsics: camera intrinsics (default: the recording's).
        distortion: known lens distortion (OpenCV order), used for the board poses.
        calibrate_intrinsics: estimate the intrinsics and distortion from the board views
            (``cv2.calibrateCamera``) after the checks, starting at ``intrinsics``.
        max_offset_s: largest offset searched by ``"auto"``, seconds.

    Returns:
        The ``CalibrationResult`` (as the depth path; its calibration carries the
        intrinsics, distortion and time offset used) and a ``BoardReport``.

    Raises:
        ValueError: any of the refusals (too few views with the board, a spec whose scale
            does not match, zones missing the board's surface, too similar plane
            orientations), with the reason and what to record instead.
    """
    meta = recording.meta
    fov = tuple(fov_deg) if fov_deg is not None else tuple(meta.fov_deg)
    camera = intrinsics or meta.intrinsics
    detector = BoardDetector(spec)
    cache: dict = {}

    def detect(path) -> BoardDetection | None:
        if path not in cache:
            import cv2

            # Any depth kept, so a 16-bit image (a depth map in color/) is refused, not
            # scaled to 8 bits and searched in vain for the board.
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
            if image is None:
                raise ValueError(f"{path}: unreadable image")
            if image.dtype != np.uint8:  # read as it is, for its channels
                from deltar.io.input_file import not_8bit_colour

                full = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                raise ValueError(not_8bit_colour(path, image.dtype, 1 if full is None or
                                                 full.ndim == 2 else full.shape[2]))
            if image.shape != (camera.height, camera.width):
                raise ValueError(f"{path} is {image.shape[0]}x{image.shape[1]}, the "
                                 f"intrinsics are for {camera.height}x{camera.width}")
            cache[path] = detector.detect(image)
        return cache[path]

    frames = recording.zone_frames()
    estimate = None
    if time_offset_s == "auto":
        found = [(t, d) for t, p in zip(recording.color_times_s, recording.color_paths,
                                        strict=True) if (d := detect(p)) is not None]
        detector.refuse_few_views(recording, len(found), len(recording.color_paths),
                                  MIN_BOARD_VIEWS)
        cam_t = np.array([t for t, _ in found])
        poses = [estimate_board_pose(d, camera, distortion) for _, d in found]
        cam_d = np.array([p.offset_cam_m for p in poses])
        zone_t, zone_d = [], []
        for frame in frames:
            try:
                plane = zone_plane_from_frame(frame, fov_deg=fov, zone_model=True)
            except ValueError:
                continue
            zone_t.append(frame.timestamp_s)
            zone_d.append(plane.offset_m)
        estimate = estimate_time_offset(cam_t, cam_d, np.array(zone_t), np.array(zone_d),
                                        camera_normals=np.array([p.normal_cam for p in poses]),
                                        max_offset_s=max_offset_s)
        offset = estimate.offset_s
    else:
        offset = float(time_offset_s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unpaired frames are counted below
        pairs = recording.pairs(tolerance_s, time_offset_s=offset)
    if not pairs:  # not the board's fault: say what did not pair
        from deltar.io.recording import no_pairs_message

        raise ValueError(no_pairs_message(recording, tolerance_s, offset))
    unpaired = len(frames) - len(pairs)

    views: list[_View] = []
    skipped: list[tuple[str, str]] = []
    searched = 0
    for pair in pairs:
        frame = pair.zone_frame
        name = f"t={frame.timestamp_s:.3f}s"
        searched += 1
        detection = detect(pair.color_path)
        if detection is None:
            skipped.append((name, f"frame {name}: the board is not found in "
                                  f"{pair.color_path.name}"))
            continue
        pose = estimate_board_pose(detection, camera, distortion)
        try:
            plane = zone_plane_from_frame(frame, fov_deg=fov, zone_model=True, name=name)
            reason = ""
        except ValueError as err:
            plane, reason = None, str(err)
        views.append(_View(name, plane, pose, detection, frame.flat()[0], reason))
    detector.refuse_few_views(recording, len(views), searched, MIN_BOARD_VIEWS, paired=True)
    intrinsics_rms = camera_fit = None
    if calibrate_intrinsics:
        # Board poses from intrinsics that are several % off disagree with the zones'
        # planes, so the camera is calibrated before the views are checked against them.
        detections = [d for d in cache.values() if d is not None]
        if len(detections) < MIN_INTRINSIC_VIEWS:
            raise ValueError(f"--calibrate-intrinsics needs the board in at least "
                             f"{MIN_INTRINSIC_VIEWS} images, found in {len(detections)}")
        camera_fit = calibrate_camera(detections, camera)
        camera, distortion = camera_fit.intrinsics, camera_fit.distortion
        intrinsics_rms = camera_fit.rms_px
        for v in views:
            v.pose = estimate_board_pose(v.detection, camera, distortion)
    # Zones that see another surface give planes whose normals disagree with the board's.
    with_plane = [v for v in views if v.plane is not None]
    _, facing = _agreeing(with_plane, offsets=False)
    _refuse_missing(views, [v for v, ok in zip(with_plane, facing, strict=True) if ok])
    # The board's printed size sets the camera's distances; the zones measure theirs.
    facing_views = [v for v, ok in zip(with_plane, facing, strict=True) if ok]
    ratio = float(np.median([v.pose.offset_cam_m / v.plane.offset_m for v in facing_views]))
    if not 1 / MAX_SCALE_RATIO <= ratio <= MAX_SCALE_RATIO:
        raise ValueError(
            f"the board spec {spec.text()} does not match what is detected: with "
            f"{1000 * spec.square_m:g} mm squares the board would be {ratio:.2f} times "
            "as far from the camera as the zones measure the surface it is on; measure "
            f"a printed square (about {1000 * spec.square_m / ratio:.1f} mm if the camera "
            "intrinsics are right) and give that as SQUARE_M (and MARKER_M) in --target")
    closed, agree = _agreeing(with_plane)
    good = [v for v, ok in zip(with_plane, agree, strict=True) if ok]
    _refuse_missing(views, good)
    for v in views:
        if v not in good:
            skipped.append((v.name, v.reason or f"frame {v.name}: the zones' plane disagrees "
                            "with the board's plane (the zones see another surface)"))
    normals_sensor = np.array([v.pose.normal_cam for v in good]) @ closed.rotation
    try:
        check_plane_diversity(normals_sensor)
    except ValueError:
        seen = normal_spread_deg(normals_sensor)
        raise ValueError(
            f"the board was seen from too few directions: its {len(good)} views give plane "
            f"orientations (as the sensor sees them) spread {seen[0]:.1f} and {seen[1]:.1f} "
            f"deg rms, at least 5.7 deg rms is needed both ways (views tilted 25-45 deg "
            "left, right, up and down, not all head-on): record the board from more "
            "directions") from None

    # The long part: the robust refinement.
    weights = np.array([_frame_weight(v, fov) for v in good])
    observations = [_observation(v, closed, fov, w / weights.mean())
                    for v, w in zip(good, weights, strict=True)]
    result = calibrate_observations(observations, nominal, camera, grid=meta.grid,
                                    fov_deg=fov, sensor_model=meta.sensor_model,
                                    skipped=skipped, start=closed)
    result.unpaired = unpaired
    used = {o.name for o in result.observations}
    result = _refine_to_zones(result, [v for v in good if v.name in used], fov)
    calibration = result.calibration
    residuals = dict(calibration.residuals)
    residuals["board_views"] = float(len(views))
    residuals["board_pose_rms_px"] = float(np.median([v.pose.reprojection_rms_px
                                                      for v in good]))
    if intrinsics_rms is not None:
        residuals["intrinsics_rms_px"] = intrinsics_rms
    used_views = [v for v in good if v.name in used]
    uncertainty = _expected_error(used_views, calibration, fov, camera_fit)
    scale_error = warn_board_scale(np.array([v.pose.normal_cam for v in used_views]),
                                   np.array([v.pose.offset_cam_m for v in used_views]),
                                   np.array([v.plane.offset_m for v in used_views]), spec)
    if scale_error is not None:  # left out when too few views judged it
        residuals["board_scale_translation_m"] = scale_error
    residuals["rotation_sd_deg"] = uncertainty.rotation_rms_deg
    residuals["translation_sd_m"] = uncertainty.translation_rms_m
    residuals["zone_noise_m"] = uncertainty.zone_noise_m
    result.calibration = replace(calibration, residuals=residuals,
                                 distortion=tuple(distortion), time_offset_s=offset)
    report = BoardReport(searched, len(views), residuals["board_pose_rms_px"], estimate, offset,
                         intrinsics_rms, closed, skipped, uncertainty, camera_fit)
    return result, report


def _refine_to_zones(result: CalibrationResult, views: list[_View], fov) -> CalibrationResult:
    """The plane-pair solution refined against the zone readings themselves: each view's
    board plane, moved into the sensor frame, predicts every zone's reading
    (:mod:`deltar.calibration.zone_model`); all views jointly."""
    calibration = result.calibration
    model = ZoneReadingModel(grid=calibration.grid, fov_deg=tuple(fov))
    refined = refine_extrinsics_to_zones(
        [(v.pose.normal_cam, v.pose.offset_cam_m) for v in views], [v.mean_m for v in views],
        [v.plane.inliers for v in views], calibration.extrinsics, model)
    after = mean_zone_to_cloud_distance(result.observations, refined.extrinsics)
    residuals = dict(calibration.residuals)
    residuals["zone_to_cloud_after_m"] = after
    residuals["point_to_plane_rms_m"] = point_to_plane_rms(result.observations,
                                                           refined.extrinsics)
    residuals["zone_reading_rms_m"] = refined.rms_residual_m
    return replace(result, calibration=replace(calibration, extrinsics=refined.extrinsics,
                                               residuals=residuals),
                   distance_after_m=after)


def _expected_error(views: list[_View], calibration, fov,
                    camera_fit: CameraCalibration | None = None) -> ExtrinsicUncertainty:
    """The extrinsic's expected error from the views used (with the error of intrinsics
    calibrated from the same views, ``camera_fit``); warns when it is large, saying
    whether more views or views that pin the camera down are needed."""
    planes = [(v.pose.normal_cam, v.pose.offset_cam_m, v.pose.normal_std_rad,
               v.pose.offset_std_m) for v in views]
    args = ([v.mean_m for v in views], [v.plane.inliers for v in views],
            calibration.extrinsics)
    kwargs = {"grid": calibration.grid, "fov_deg": fov}
    uncertainty = zones_only = extrinsic_uncertainty(planes, *args, **kwargs)
    if camera_fit is not None:
        sensitivity = [board_plane_sensitivity(v.detection, camera_fit) for v in views]
        uncertainty = extrinsic_uncertainty(planes, *args, **kwargs,
                                            zone_noise_m=zones_only.zone_noise_m,
                                            plane_sensitivity=sensitivity,
                                            camera_covariance=camera_fit.covariance)
    rotation, translation = uncertainty.rotation_rms_deg, uncertainty.translation_rms_m
    if rotation <= MAX_EXPECTED_ROTATION_DEG and translation <= MAX_EXPECTED_TRANSLATION_M:
        return uncertainty
    wanted = (f"(1 sd; at most {MAX_EXPECTED_ROTATION_DEG} deg and "
              f"{1000 * MAX_EXPECTED_TRANSLATION_M:g} mm wanted)")
    more_views = "record more views, tilted 25-45 deg left, right, up and down"
    if camera_fit is None:
        warnings.warn(
            f"the {len(views)} board views leave the extrinsic uncertain: the zones' noise "
            f"({100 * uncertainty.zone_noise_m:.1f} cm) allows errors of about "
            f"{rotation:.2f} deg and {1000 * translation:.1f} mm {wanted}: {more_views}",
            stacklevel=3)
        return uncertainty
    # Name both parts (root of the summed rotation variances) and advise on the larger.
    zones_part = zones_only.covariance[:3, :3].trace()
    camera_part = max(uncertainty.covariance[:3, :3].trace() - zones_part, 0.0)
    close_views = ("record views close enough that the board fills most of the image "
                   f"(about {NEAR_VIEW_M[0]:g}-{NEAR_VIEW_M[1]:g} m for an A4 board), tilted "
                   "as the others")
    advice = (f"{close_views}, or give intrinsics from a camera calibration; more views "
              "also help" if camera_part > zones_part else
              f"{more_views}; views close enough that the board fills most of the image "
              f"(about {NEAR_VIEW_M[0]:g}-{NEAR_VIEW_M[1]:g} m for an A4 board) pin the "
              "intrinsics down")
    sd = camera_fit.sd
    warnings.warn(
        f"the {len(views)} board views leave the extrinsic uncertain: the zones' noise "
        f"({100 * uncertainty.zone_noise_m:.1f} cm) allows errors of about "
        f"{np.degrees(np.sqrt(zones_part)):.2f} deg, and the camera intrinsics calibrated "
        f"from the same views (principal point sd {sd[2]:.1f}, {sd[3]:.1f} px) "
        f"{np.degrees(np.sqrt(camera_part)):.2f} deg; together {rotation:.2f} deg and "
        f"{1000 * translation:.1f} mm {wanted}: {advice}", stacklevel=3)
    return uncertainty


def _frame_weight(view: _View, fov) -> float:
    """Inverse variance of the refinement's residuals for this view: the offset's, plus
    the normal's over the lateral extent of the sensor's view on the plane."""
    normal_var, offset_var = view.variances()
    radius = view.plane.offset_m * np.tan(np.deg2rad(max(fov) / 2)) * 0.6
    return 1.0 / (offset_var + radius ** 2 * normal_var)


def _observation(view: _View, extrinsics: SensorExtrinsics, fov,
                 weight: float = 1.0) -> PlaneObservation:
    """A view as the refinement's plane observation: the board's plane sampled where the
    sensor's rays meet it (coarse for the solve, fine for the zone-to-cloud report)."""
    args = (view.pose.normal_cam, view.pose.offset_cam_m, extrinsics.rotation,
            extrinsics.translation_m, fov)
    zones = zone_centre_points(view.mean_m, fov)[view.plane.inliers]
    # Sample a little beyond the field of view: the nominal guess places the zones
    # elsewhere, and the report looks for their nearest plane point.
    wide = (fov[0] + 20.0, fov[1] + 20.0)
    cloud = board_points_in_view(*args[:4], wide, 160)
    return PlaneObservation(view.plane.normal, view.plane.offset_m,
                            board_points_in_view(*args, 24), zones, cloud_cam_m=cloud,
                            name=view.name, weight=weight)


def _refuse_missing(views: list[_View], good: list[_View]) -> None:
    """Refuse when the zones miss the board's surface in most views (or too few are left)."""
    missing = len(views) - len(good)
    if missing > len(views) / 2 or len(good) < MIN_BOARD_VIEWS:
        reasons = [v.reason for v in views if v.reason][:1] or \
            ["the zones' plane disagrees with the board's plane"]
        raise ValueError(
            f"in {missing} of the {len(views)} views with the board the zones mostly miss "
            f"the surface the board is fixed on (first: {reasons[0]}), leaving "
            f"{len(good)} usable views (need {MIN_BOARD_VIEWS}): fix the board flat on a "
            "wall, door or table that fills the sensor's whole view around it, and keep "
            "other objects out of that view; if it is, the recording's camera intrinsics "
            "may be off (try --calibrate-intrinsics) or its clocks apart (try --time-offset "
            "auto)")
