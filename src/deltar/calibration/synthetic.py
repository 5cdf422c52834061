"""Synthetic rigs for testing calibration: render depth as seen by the camera and the sensor.

The sensor is modelled as a virtual pinhole camera whose image covers exactly its field
of view, split into ``grid x grid`` zone rectangles; rendering z-depth there and running
``deltar.sensor.simulate`` gives the zone frame the sensor would report.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltar.camera import CameraIntrinsics, pixel_rays
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics, zone_angles_deg
from deltar.sensor.zone_frame import ZoneFrame

#: The sensor model of the synthetic rigs' readings and recordings: a simulated sensor
#: beside the camera at the rig's extrinsic, not on its axis as ``deltar record
#: --simulate``'s ("simulated"), so replaying them needs their calibration.
SYNTHETIC_RIG_SENSOR = "simulated-rig"


def sensor_virtual_camera(grid: int = 8, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                          pixels_per_zone: int = 16) -> tuple[CameraIntrinsics, np.ndarray]:
    """A pinhole camera whose image is the sensor's field of view, and its zone rectangles.

    Args:
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) field of view in degrees.
        pixels_per_zone: image pixels per zone along each side (on average).

    Returns:
        The virtual camera's intrinsics and (grid * grid, 4) float32 zone rectangles
        (y0, x0, y1, x1) in its pixels (zones are even in angle, so slightly uneven in
        pixels).
    """
    size = grid * pixels_per_zone
    tan_x, tan_y = (np.tan(np.deg2rad(f / 2)) for f in fov_deg)
    # The image border (-0.5 and size - 0.5) lies exactly on the field of view's edge.
    intr = CameraIntrinsics(size / 2 / tan_x, size / 2 / tan_y, (size - 1) / 2,
                            (size - 1) / 2, size, size)
    angles = np.tan(np.deg2rad(zone_angles_deg(grid, fov_deg)))
    rects = np.stack([intr.fy * angles[:, 0] + intr.cy, intr.fx * angles[:, 1] + intr.cx,
                      intr.fy * angles[:, 2] + intr.cy, intr.fx * angles[:, 3] + intr.cx],
                     axis=1)
    return intr, rects.astype(np.float32)


def render_planes_depth(planes_world: np.ndarray, cam_to_world: np.ndarray,
                        intrinsics: CameraIntrinsics, max_depth_m: float = 20.0) -> np.ndarray:
    """Z-depth of the nearest plane in front of a camera (a convex room seen from inside).

    Args:
        planes_world: (P, 4) planes ``(nx, ny, nz, d)`` with ``n . x + d = 0`` in the world.
        cam_to_world: (4, 4) camera pose (camera-to-world).
        intrinsics: the camera's intrinsics.
        max_depth_m: depth beyond this is invalid (0).

    Returns:
        (H, W) float32 z-depth in metres, 0 where nothing is hit.
    """
    planes = np.asarray(planes_world, dtype=np.float64).reshape(-1, 4)
    rot, origin = cam_to_world[:3, :3], cam_to_world[:3, 3]
    rays_world = pixel_rays(intrinsics) @ rot.T  # z = 1 rays, so the hit distance is z-depth
    denom = rays_world @ planes[:, :3].T  # (H, W, P)
    numer = -(planes[:, :3] @ origin + planes[:, 3])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = numer / denom
    t = np.where((t > 1e-6) & np.isfinite(t), t, np.inf).min(axis=-1)
    return np.where(t < max_depth_m, t, 0.0).astype(np.float32)


def render_points_depth(points_m: np.ndarray, intrinsics: CameraIntrinsics,
                        splat_px: int = 1) -> np.ndarray:
    """Z-buffer a point cloud into a depth map (nearest point per pixel).

    Args:
        points_m: (N, 3) points in the camera frame, metres.
        intrinsics: the camera's intrinsics.
        splat_px: each point also fills this many neighbouring pixels on every side, so
            sparse clouds leave no holes.

    Returns:
        (H, W) float32 z-depth in metres, 0 where no point lands.
    """
    pts = np.asarray(points_m, dtype=np.float64)
    pts = pts[pts[:, 2] > 1e-6]
    u = np.round(intrinsics.fx * pts[:, 0] / pts[:, 2] + intrinsics.cx).astype(np.int64)
    v = np.round(intrinsics.fy * pts[:, 1] / pts[:, 2] + intrinsics.cy).astype(np.int64)
    # Cull points that land nowhere near the image before the (slow) scattered minimum.
    near = (u >= -splat_px) & (u < intrinsics.width + splat_px) & (v >= -splat_px) & \
        (v < intrinsics.height + splat_px)
    pts, u, v = pts[near], u[near], v[near]
    depth = np.full(intrinsics.height * intrinsics.width, np.inf)
    for dv in range(-splat_px, splat_px + 1):
        for du in range(-splat_px, splat_px + 1):
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < intrinsics.width) & (vv >= 0) & (vv < intrinsics.height)
            np.minimum.at(depth, vv[ok] * intrinsics.width + uu[ok], pts[ok, 2])
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(intrinsics.height, intrinsics.width).astype(np.float32)


def sensor_pose(cam_to_world: np.ndarray, extrinsics: SensorExtrinsics) -> np.ndarray:
    """(4, 4) sensor-to-world pose from the camera pose and the sensor-to-camera extrinsics."""
    sensor_to_cam = np.eye(4)
    sensor_to_cam[:3, :3] = extrinsics.rotation
    sensor_to_cam[:3, 3] = extrinsics.translation_m
    return np.asarray(cam_to_world, dtype=np.float64) @ sensor_to_cam


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0),
            ) -> np.ndarray:
    """(4, 4) camera-to-world pose of a camera at ``eye`` looking at ``target``.

    Camera axes: x right, y down, z forward; ``up`` is the world direction that appears
    up in the image.
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


#: A 5 m x 2.6 m x 6 m box room, planes ``(nx, ny, nz, d)`` (``n . x + d = 0``) with the
#: normals pointing inwards; world y points down (like a level camera's y axis).
BOX_ROOM = np.array([[-1.0, 0, 0, 2.5], [1.0, 0, 0, 2.5],    # walls x = +-2.5
                     [0, -1.0, 0, 1.3], [0, 1.0, 0, 1.3],    # floor y = 1.3, ceiling -1.3
                     [0, 0, -1.0, 3.0], [0, 0, 1.0, 3.0]])   # walls z = +-3


@dataclass(frozen=True)
class SyntheticRigFrame:
    """One synthetic capture of a camera + ToF rig.

    Attributes:
        zone_frame: the simulated sensor reading (z-depth means, metres).
        depth_m: (H, W) float32 camera depth (z-depth, metres, 0 invalid).
        cam_to_world: (4, 4) camera pose.
        plane_index: index of the room plane the rig was pointed at.
    """

    zone_frame: ZoneFrame
    depth_m: np.ndarray
    cam_to_world: np.ndarray
    plane_index: int


def synthetic_rig_frames(
    extrinsics: SensorExtrinsics,
    camera: CameraIntrinsics,
    *,
    planes: np.ndarray = BOX_ROOM,
    view_planes: tuple[int, ...] | None = None,
    frames_per_plane: int = 4,
    distance_m: float = 1.6,
    tilt_deg: float = 25.0,
    mean_noise_m: float = 0.02,
    invalid_fraction: float = 0.1,
    grid: int = 8,
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
    pixels_per_zone: int = 16,
    seed: int = 0,
) -> list[SyntheticRigFrame]:
    """Simulate a rig scanning the planes of a room, a few frames per plane.

    Each frame points the camera at a random spot near the centre of one plane from about
    ``distance_m`` away, viewed up to about ``tilt_deg`` off the plane's normal in each of
    two directions; the sensor's zones
    are simulated with ``deltar.sensor.simulate`` from the z-depth it would see, then
    ``mean_noise_m`` Gaussian noise is added to every zone mean and ``invalid_fraction``
    of the zones are marked invalid at random.

    Args:
        extrinsics: the true sensor-to-camera transform.
        camera: the camera's intrinsics (sets the depth map size).
        planes: (P, 4) room planes with inward normals.
        view_planes: indices of the planes to scan (all when None).
        frames_per_plane: captures per scanned plane.
        distance_m: camera distance from the plane, metres.
        tilt_deg: largest viewing angle off the plane's normal per direction, degrees.
        mean_noise_m: std of the noise added to zone means, metres.
        invalid_fraction: fraction of zones randomly made invalid.
        grid, fov_deg: sensor zone grid and field of view (degrees).
        pixels_per_zone: resolution of the sensor's virtual depth image.
        seed: random seed.

    Returns:
        The frames, timestamps 0, 1, 2, ... seconds.
    """
    rng = np.random.default_rng(seed)
    sensor_cam, rects = sensor_virtual_camera(grid, fov_deg, pixels_per_zone)
    indices = range(len(planes)) if view_planes is None else view_planes
    frames = []
    for index in indices:
        normal, offset = planes[index, :3], planes[index, 3]
        tangent_a = np.cross(normal, [0.3, 0.5, 0.8])
        tangent_a /= np.linalg.norm(tangent_a)
        tangent_b = np.cross(normal, tangent_a)
        for _ in range(frames_per_plane):
            target = -offset * normal + rng.uniform(-0.4, 0.4, 2) @ np.stack(
                [tangent_a, tangent_b])
            jitter = np.tan(np.deg2rad(tilt_deg)) * rng.uniform(-1.0, 1.0, 2)
            direction = normal + jitter @ np.stack([tangent_a, tangent_b])
            eye = target + distance_m * direction / np.linalg.norm(direction)
            up = (0.0, 0.0, 1.0) if abs(normal[1]) > 0.5 else (0.0, -1.0, 0.0)
            pose = look_at(eye, target, up)
            depth = render_planes_depth(planes, pose, camera)
            frame = simulated_zone_frame(planes, sensor_pose(pose, extrinsics), sensor_cam,
                                         rects, float(len(frames)), rng,
                                         mean_noise_m=mean_noise_m,
                                         invalid_fraction=invalid_fraction)
            frames.append(SyntheticRigFrame(frame, depth, pose, int(index)))
    return frames


def simulated_zone_frame(planes: np.ndarray, sensor_to_world: np.ndarray,
                         sensor_cam: CameraIntrinsics, rects: np.ndarray, timestamp_s: float,
                         rng: np.random.Generator, *, mean_noise_m: float = 0.02,
                         invalid_fraction: float = 0.1) -> ZoneFrame:
    """The zone frame a sensor at ``sensor_to_world`` (4, 4) reads in a room of ``planes``.

    Zones are simulated (``deltar.sensor.simulate``) from the sensor's z-depth rendered in
    its virtual camera (:func:`sensor_virtual_camera`), then ``invalid_fraction`` of them
    are made invalid at random and Gaussian noise of ``mean_noise_m`` (metres) is added to
    the means.
    """
    from deltar.sensor.simulate_frame import simulate_zone_frame

    sensor_depth = render_planes_depth(planes, sensor_to_world, sensor_cam)
    clean = simulate_zone_frame(sensor_depth, rects, timestamp_s=timestamp_s)
    mean, sigma, valid = clean.flat()
    valid = valid & (rng.random(valid.size) >= invalid_fraction)
    noisy = np.clip(mean + rng.normal(0.0, mean_noise_m, mean.size), 1e-3, None)
    return ZoneFrame(np.where(valid, noisy, 0.0), np.where(valid, sigma, 0.0), valid,
                     timestamp_s=timestamp_s, sensor_model=SYNTHETIC_RIG_SENSOR,
                     no_target=clean.flat_no_target() & ~valid)


def write_synthetic_recording(folder, frames: list[SyntheticRigFrame], camera: CameraIntrinsics,
                              *, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                              with_depth: bool = True) -> None:
    """Write synthetic rig frames as a recording folder (``deltar.io.recording`` layout).

    Colour images are grey levels of the camera depth (near = bright), enough to see the
    zone layout; colour and depth share the zone frame's timestamp.
    """
    from deltar.io.recording import RecordingMeta, RecordingWriter

    grid = frames[0].zone_frame.grid if frames else 8
    writer = RecordingWriter(folder, RecordingMeta(camera, SYNTHETIC_RIG_SENSOR, grid, fov_deg))
    for item in frames:
        t = float(item.zone_frame.timestamp_s)
        writer.add_zone_frame(item.zone_frame)
        grey = np.clip(255 * (1 - item.depth_m / 6.0), 0, 255).astype(np.uint8)
        writer.add_color(t, np.repeat(grey[..., None], 3, axis=2))
        if with_depth:
            writer.add_depth(t, item.depth_m)
