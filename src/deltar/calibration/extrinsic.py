"""Sensor-to-camera extrinsics from planes (DELTAR Eq. 2).

For every usable frame i we have a plane ``(n_i, d_i)`` fitted to the zone frame in the
sensor frame (``deltar.calibration.plane``) and points ``P_i`` of that plane in the camera
frame (from the depth camera, or from a SLAM map and the camera pose). The extrinsics
minimise the robust sum of point-to-plane distances
``n_i . (R_cs p + t_cs) + d_i`` over all frames and points, where ``(R_cs, t_cs)`` maps
camera to sensor coordinates; the result is returned as ``SensorExtrinsics``
(sensor to camera, ``p_cam = R p_sensor + t``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deltar.calibration.plane import ZonePlaneFit, ransac_plane, zone_centre_points
from deltar.camera import CameraIntrinsics, backproject
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics

#: Smallest singular value (of the stacked unit plane normals in the sensor frame divided
#: by sqrt(frames)) accepted: about a +-10 degree spread of plane orientations as seen from
#: the sensor. Less leaves rotation or translation barely constrained (with 2 cm zone
#: noise the translation error grows past 1 cm).
MIN_NORMAL_SPREAD = 0.1


@dataclass(frozen=True)
class PlaneObservation:
    """One frame's plane seen by both devices.

    Attributes:
        normal_sensor: (3,) unit plane normal in the sensor frame.
        offset_sensor_m: plane offset d (``n . p + d = 0``) in metres, sensor frame.
        points_cam_m: (N, 3) points of that plane in the camera frame, metres.
        zone_points_sensor_m: (M, 3) the frame's inlier zone measurements (zone centre
            ray at the zone mean) in the sensor frame, metres; used for reporting.
        cloud_cam_m: (K, 3) the scene points near the sensor's view in the camera frame
            (for the zone-to-cloud distance report); defaults to ``points_cam_m``.
        name: label for messages (e.g. the timestamp).
        weight: relative weight of the frame in the solve (1 for every depth-image or
            SLAM frame; board views weigh by their planes' uncertainty).
    """

    normal_sensor: np.ndarray
    offset_sensor_m: float
    points_cam_m: np.ndarray
    zone_points_sensor_m: np.ndarray
    cloud_cam_m: np.ndarray | None = None
    name: str = ""
    weight: float = 1.0


@dataclass(frozen=True)
class ExtrinsicResult:
    """Result of ``solve_extrinsics``.

    Attributes:
        extrinsics: the solved sensor-to-camera transform.
        rms_point_to_plane_m: RMS of the point-to-plane residuals after solving, metres.
        frames_used: number of plane observations in the final solve.
        success: scipy's convergence flag.
        rejected: names of frames dropped because their planes disagreed with the rest.
    """

    extrinsics: SensorExtrinsics
    rms_point_to_plane_m: float
    frames_used: int
    success: bool
    rejected: tuple[str, ...] = ()


def nominal_extrinsics(roll_deg: float = 90.0,
                       translation_m: Sequence[float] = (0.0, 0.0, 0.0)) -> SensorExtrinsics:
    """The nominal rig: same viewing direction, sensor rolled ``roll_deg`` about it.

    Args:
        roll_deg: rotation about the common optical (z) axis in degrees, sensor to camera.
        translation_m: (3,) sensor origin in the camera frame, metres.
    """
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_euler("z", roll_deg, degrees=True).as_matrix()
    return SensorExtrinsics(rotation, np.asarray(translation_m, dtype=np.float64))


def check_plane_diversity(normals: np.ndarray) -> None:
    """Raise ``ValueError`` saying what to record if the planes cannot fix R and t.

    What matters is how the planes are oriented *relative to the sensor*: every frame's
    normal in the sensor frame constrains the translation along it and the rotation
    about the others. Facing each wall head-on gives the same sensor-frame normal every
    time, however many walls there are; tilting the rig or using differently oriented
    planes varies it.

    Args:
        normals: (F, 3) unit plane normals in the sensor frame (the sign does not matter).
    """
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if normals.shape[0] < 3:
        raise ValueError(f"only {normals.shape[0]} usable plane frames: record at least three "
                         "planes with different orientations (e.g. two walls and the floor)")
    spread = np.linalg.svd(normals / np.sqrt(normals.shape[0]), compute_uv=False)
    seen = normal_spread_deg(normals)
    needed = f"at least {np.degrees(np.arcsin(MIN_NORMAL_SPREAD)):.1f} deg rms is needed"
    if spread[1] < MIN_NORMAL_SPREAD:
        raise ValueError("all planes are parallel as seen from the sensor: record at least "
                         "three planes with different orientations (e.g. two walls and the "
                         "floor), viewed at 20-40 degrees rather than head-on (the normals "
                         f"spread {seen[0]:.1f} and {seen[1]:.1f} deg rms about their mean "
                         f"direction; {needed} in both directions)")
    if spread[2] < MIN_NORMAL_SPREAD:
        raise ValueError("the plane normals all lie in one plane as seen from the sensor "
                         "(e.g. only walls, or the rig only panned left-right), so one "
                         "direction is unconstrained: also record a plane of another "
                         "orientation, such as the floor, or tilt the rig up and down (the "
                         f"normals spread {seen[0]:.1f} deg rms one way but {seen[1]:.1f} "
                         f"deg the other; {needed} in both directions)")


def normal_spread_deg(normals: np.ndarray) -> tuple[float, float]:
    """How much plane orientations vary: rms angle (degrees) of the unit normals from their
    mean direction along the two principal directions across it, largest first.

    ``check_plane_diversity`` needs both above ``degrees(arcsin(MIN_NORMAL_SPREAD))``
    (5.7 deg rms, about views tilted +-10 deg uniformly).

    Args:
        normals: (F, 3) unit normals (the sign does not matter).
    """
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    spread = np.linalg.svd(normals / np.sqrt(max(normals.shape[0], 1)), compute_uv=False)
    return tuple(float(np.degrees(np.arcsin(min(1.0, v)))) for v in spread[1:3])


def closed_form_extrinsics(normals_sensor: np.ndarray, offsets_sensor_m: np.ndarray,
                           normals_cam: np.ndarray, offsets_cam_m: np.ndarray,
                           normal_weights: np.ndarray | None = None,
                           offset_weights: np.ndarray | None = None) -> SensorExtrinsics:
    """Sensor-to-camera transform from planes seen by both devices.

    A plane ``n_c . p + d_c = 0`` in the camera frame is ``(R^T n_c) . p + (d_c + n_c . t)
    = 0`` in the sensor frame, so ``n_c = R n_s`` (the rotation aligning the normals,
    Kabsch) and ``n_c . t = d_s - d_c`` (linear least squares for t).

    Args:
        normals_sensor, normals_cam: (F, 3) unit normals, both oriented towards their
            device (the devices are on the same side of every plane).
        offsets_sensor_m, offsets_cam_m: (F,) plane offsets d, metres.
        normal_weights, offset_weights: optional (F,) weights (inverse variances) of the
            normal and offset equations.

    Returns:
        ``SensorExtrinsics`` (``p_cam = R p_sensor + t``).
    """
    ns = np.asarray(normals_sensor, dtype=np.float64).reshape(-1, 3)
    nc = np.asarray(normals_cam, dtype=np.float64).reshape(-1, 3)
    if ns.shape != nc.shape or ns.shape[0] < 3:
        raise ValueError(f"need at least 3 plane pairs of equal count, got {ns.shape[0]} and "
                         f"{nc.shape[0]}")
    wn = np.ones(len(ns)) if normal_weights is None else np.asarray(normal_weights, float)
    wd = np.ones(len(ns)) if offset_weights is None else np.asarray(offset_weights, float)
    u, _, vt = np.linalg.svd((ns * wn[:, None]).T @ nc)
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, sign]) @ u.T
    rhs = np.asarray(offsets_sensor_m, float) - np.asarray(offsets_cam_m, float)
    root = np.sqrt(wd)
    translation = np.linalg.lstsq(nc * root[:, None], rhs * root, rcond=None)[0]
    return SensorExtrinsics(rotation, translation)


def solve_extrinsics(
    observations: Sequence[PlaneObservation],
    nominal: SensorExtrinsics,
    *,
    loss: str = "soft_l1",
    loss_scale_m: float = 0.02,
    max_points_per_frame: int = 400,
    frame_outlier_m: float = 0.03,
    seed: int = 0,
) -> ExtrinsicResult:
    """Solve the sensor-to-camera extrinsics by robust point-to-plane least squares.

    A frame whose sensor plane was fitted to the wrong surface disagrees with all the
    others as a whole, which a per-point robust loss cannot undo; so after each solve,
    frames whose RMS residual exceeds both ``frame_outlier_m`` and three times the
    median frame RMS are dropped and the solve is repeated (at most three rounds).

    Args:
        observations: per-frame planes (sensor frame) and camera-frame points on them.
        nominal: starting guess (e.g. ``nominal_extrinsics(90)``).
        loss: scipy ``least_squares`` loss ("linear", "soft_l1", "huber", "cauchy").
        loss_scale_m: residual scale in metres where the robust loss bends.
        max_points_per_frame: camera points used per frame (random subset, fixed seed), so
            every frame weighs about the same.
        frame_outlier_m: frame RMS residual (metres) below which a frame is never dropped.
        seed: random seed of the subsets.

    Returns:
        ``ExtrinsicResult``.

    Raises:
        ValueError: too few frames, or planes whose orientations cannot fix the transform
            (the message says what to record).
    """
    rng = np.random.default_rng(seed)
    frames = []
    for obs in observations:
        p = np.asarray(obs.points_cam_m, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3:
            raise ValueError(f"observation {obs.name!r}: points_cam_m must be (N >= 3, 3)")
        if p.shape[0] > max_points_per_frame:
            p = p[rng.choice(p.shape[0], max_points_per_frame, replace=False)]
        frames.append((obs, p))
    rejected: list[str] = []
    start = nominal
    for _ in range(3):
        check_plane_diversity(np.array([o.normal_sensor for o, _ in frames]))
        extrinsics, success = _solve_once(frames, start, loss, loss_scale_m)
        frame_rms = np.array([np.sqrt(np.mean(_plane_residuals(o, p, extrinsics) ** 2))
                              for o, p in frames])
        bad = (frame_rms > frame_outlier_m) & (frame_rms > 3 * np.median(frame_rms))
        if not bad.any():
            break
        rejected += [o.name for (o, _), b in zip(frames, bad, strict=True) if b]
        frames = [f for f, b in zip(frames, bad, strict=True) if not b]
        start = extrinsics
    residuals = np.concatenate([_plane_residuals(o, p, extrinsics) for o, p in frames])
    return ExtrinsicResult(extrinsics, float(np.sqrt(np.mean(residuals ** 2))), len(frames),
                           success, tuple(rejected))


def _plane_residuals(obs: PlaneObservation, points_cam: np.ndarray,
                     extrinsics: SensorExtrinsics) -> np.ndarray:
    """Signed distances (metres) of camera points to the frame's sensor plane."""
    sensor = (points_cam - extrinsics.translation_m) @ extrinsics.rotation
    return sensor @ np.asarray(obs.normal_sensor, float) + float(obs.offset_sensor_m)


def _solve_once(frames: list[tuple[PlaneObservation, np.ndarray]], start: SensorExtrinsics,
                loss: str, loss_scale_m: float) -> tuple[SensorExtrinsics, bool]:
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    points = np.concatenate([p for _, p in frames])
    plane_n = np.concatenate([np.repeat(np.asarray(o.normal_sensor, float)[None], len(p), 0)
                              for o, p in frames])
    plane_d = np.concatenate([np.full(len(p), float(o.offset_sensor_m)) for o, p in frames])
    scale = np.sqrt(np.concatenate([np.full(len(p), float(o.weight)) for o, p in frames]))
    inverse = start.inverse()  # camera -> sensor, the direction the residual uses
    rot0 = Rotation.from_matrix(inverse.rotation)

    def transform(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Rotation as a small rotation vector applied on top of the starting guess.
        return (Rotation.from_rotvec(x[:3]) * rot0).as_matrix(), x[3:]

    def residuals(x: np.ndarray) -> np.ndarray:
        rot, trans = transform(x)
        return scale * (np.einsum("ij,ij->i", plane_n, points @ rot.T + trans) + plane_d)

    x0 = np.concatenate([np.zeros(3), inverse.translation_m])
    solution = least_squares(residuals, x0, loss=loss, f_scale=loss_scale_m, x_scale="jac")
    rot, trans = transform(solution.x)
    return SensorExtrinsics(rot, trans).inverse(), bool(solution.success)


def point_to_plane_rms(observations: Sequence[PlaneObservation],
                       extrinsics: SensorExtrinsics) -> float:
    """RMS distance (metres) of every observation's camera points to its sensor plane
    under ``extrinsics``."""
    return float(np.sqrt(np.mean(np.concatenate(
        [_plane_residuals(o, np.asarray(o.points_cam_m, float), extrinsics) ** 2
         for o in observations]))))


def mean_zone_to_cloud_distance(observations: Sequence[PlaneObservation],
                                extrinsics: SensorExtrinsics) -> float:
    """Mean distance (metres) from each zone measurement to the nearest scene point.

    The zone measurements (``zone_points_sensor_m``) are mapped into the camera frame
    with ``extrinsics``; the paper reports this number (7.5 cm before, 1.5 cm after).
    """
    from scipy.spatial import cKDTree

    distances = []
    for obs in observations:
        cloud = obs.cloud_cam_m if obs.cloud_cam_m is not None else obs.points_cam_m
        zones = np.asarray(obs.zone_points_sensor_m, dtype=np.float64).reshape(-1, 3)
        if zones.size == 0 or len(cloud) == 0:
            continue
        cam = zones @ extrinsics.rotation.T + extrinsics.translation_m
        dist, _ = cKDTree(np.asarray(cloud, dtype=np.float64)).query(cam)
        distances.append(dist)
    if not distances:
        raise ValueError("no zone measurements to compare with the point cloud")
    return float(np.mean(np.concatenate(distances)))


def depth_to_points(depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                    stride: int = 1) -> np.ndarray:
    """Back-project a depth map into camera-frame points (:func:`deltar.camera.backproject`).

    Args:
        depth_m: (H, W) z-depth in metres, 0 = invalid; must match the intrinsics size.
        intrinsics: camera intrinsics (pixels).
        stride: keep every ``stride``-th row and column.

    Returns:
        (N, 3) float64 points in metres (valid pixels only).
    """
    return backproject(depth_m, intrinsics, stride=stride)


def points_in_sensor_view(points_cam_m: np.ndarray, extrinsics: SensorExtrinsics,
                          fov_deg: tuple[float, float] = DEFAULT_FOV_DEG, *,
                          margin_deg: float = 0.0, visible_only: bool = False,
                          occlusion_margin_m: float = 0.1) -> np.ndarray:
    """Mask of camera-frame points inside the sensor's field of view.

    Args:
        points_cam_m: (N, 3) points in the camera frame, metres.
        extrinsics: sensor-to-camera transform (e.g. the nominal guess).
        fov_deg: (horizontal, vertical) sensor field of view in degrees.
        margin_deg: shrink (> 0) or grow (< 0) the field of view on every side.
        visible_only: also drop points hidden behind nearer points (a coarse z-buffer over
            the sensor's view; needed for SLAM maps that hold the whole scene).
        occlusion_margin_m: points farther than this behind the nearest point of their
            z-buffer cell count as hidden.

    Returns:
        (N,) bool mask.
    """
    pts = np.asarray(points_cam_m, dtype=np.float64)
    sensor = (pts - extrinsics.translation_m) @ extrinsics.rotation  # R^T (p - t)
    z = sensor[:, 2]
    safe_z = np.where(z > 1e-6, z, 1.0)
    half_x = np.deg2rad(fov_deg[0] / 2 - margin_deg)
    half_y = np.deg2rad(fov_deg[1] / 2 - margin_deg)
    u, v = sensor[:, 0] / safe_z, sensor[:, 1] / safe_z
    mask = (z > 1e-6) & (np.abs(u) <= np.tan(half_x)) & (np.abs(v) <= np.tan(half_y))
    if visible_only and np.any(mask):
        cells = 32
        iu = np.clip(((u / np.tan(half_x) + 1) / 2 * cells).astype(np.int64), 0, cells - 1)
        iv = np.clip(((v / np.tan(half_y) + 1) / 2 * cells).astype(np.int64), 0, cells - 1)
        cell = iv * cells + iu
        nearest = np.full(cells * cells, np.inf)
        np.minimum.at(nearest, cell[mask], z[mask])
        mask &= z <= nearest[cell] + occlusion_margin_m
    return mask


def observation_from_points(
    plane: ZonePlaneFit,
    zone_mean_m: np.ndarray,
    cloud_cam_m: np.ndarray,
    nominal: SensorExtrinsics,
    *,
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
    threshold_m: float = 0.03,
    max_angle_deg: float = 30.0,
    max_offset_diff_m: float = 0.15,
    min_points: int = 200,
    min_point_fraction: float = 0.0,
    visible_only: bool = False,
    name: str = "",
    seed: int = 0,
) -> PlaneObservation:
    """Pair a zone-frame plane with the matching plane in a camera-frame point cloud.

    The cloud is cut to the sensor's view under the nominal extrinsics (with a few
    degrees to spare), and the dominant plane that agrees with the sensor's plane mapped
    by the nominal pose (normal within ``max_angle_deg``, offset within
    ``max_offset_diff_m``) is found by RANSAC.

    Args:
        plane: the frame's ``ZonePlaneFit`` (sensor frame).
        zone_mean_m: (Z,) zone means of the frame in metres.
        cloud_cam_m: (N, 3) scene points in the camera frame (depth camera or SLAM map).
        nominal: nominal sensor-to-camera transform.
        fov_deg: sensor field of view in degrees.
        threshold_m: RANSAC inlier distance, metres.
        max_angle_deg: largest angle between the two planes' normals under the nominal
            rotation.
        max_offset_diff_m: largest difference between the two planes' offsets under the
            nominal pose, metres (should exceed the nominal translation's error).
        min_points: fewest plane points accepted.
        min_point_fraction: fewest plane points accepted, as a fraction of the points in
            the sensor's view.
        visible_only: drop occluded points (use for SLAM maps).
        name: label for error messages.
        seed: RANSAC seed.

    Raises:
        ValueError: no matching plane with enough points (the message names ``name``).
    """
    cloud = np.asarray(cloud_cam_m, dtype=np.float64)
    view = points_in_sensor_view(cloud, nominal, fov_deg, margin_deg=-3.0,
                                 visible_only=visible_only)
    seen = cloud[view]
    if seen.shape[0] < min_points:
        raise ValueError(f"frame {name}: only {seen.shape[0]} scene points in the sensor's "
                         "view; is the depth or SLAM map covering the sensor's field of view?")
    if seen.shape[0] > 5000:  # RANSAC scoring cost grows with the point count
        seen = seen[np.random.default_rng(seed).choice(seen.shape[0], 5000, replace=False)]
    # The sensor's plane in camera coordinates under the nominal pose: R n, d - (R n) . t.
    hint = nominal.rotation @ plane.normal
    offset_hint = plane.offset_m - float(hint @ nominal.translation_m)
    try:
        _, _, inliers = ransac_plane(seen, threshold_m, normal_hint=hint,
                                     max_angle_deg=max_angle_deg, offset_hint_m=offset_hint,
                                     max_offset_diff_m=max_offset_diff_m, seed=seed)
    except ValueError as err:
        raise ValueError(f"frame {name}: no plane in the point cloud matches the sensor's "
                         f"plane: {err}") from err
    if inliers.sum() < min_points:
        raise ValueError(f"frame {name}: the matching plane has only {int(inliers.sum())} "
                         f"points (need {min_points})")
    if inliers.mean() < min_point_fraction:
        raise ValueError(f"frame {name}: the matching plane covers only {inliers.mean():.0%} of "
                         f"the scene points in the sensor's view (need "
                         f"{min_point_fraction:.0%}): fill the view with a flat surface")
    zone_points = zone_centre_points(zone_mean_m, fov_deg)[plane.inliers]
    return PlaneObservation(plane.normal, plane.offset_m, seen[inliers], zone_points,
                            cloud_cam_m=cloud[view], name=name)
