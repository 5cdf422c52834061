"""A synthetic rig looking at a printed board fixed on a wall (tests, benchmarks, docs).

The world: a wall in the plane z = 0 facing the room (z < 0), the board's printed
texture (``BoardSpec.texture``, OpenCV's own ChArUco image) on it, centred at the
origin, on a sheet of white paper. The camera image is the texture warped onto the wall
as a (distorted) pinhole camera sees it, supersampled; the zones are simulated from the
same geometry (:func:`deltar.calibration.synthetic.simulated_zone_frame`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deltar.calibration.board import BoardSpec
from deltar.calibration.synthetic import (
    SYNTHETIC_RIG_SENSOR,
    look_at,
    sensor_pose,
    sensor_virtual_camera,
    simulated_zone_frame,
)
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame

#: The wall, ``(nx, ny, nz, d)`` with the normal towards the room.
WALL = np.array([[0.0, 0.0, -1.0, 0.0]])
#: Grey level of the wall around the paper; the paper is white (255).
WALL_GREY = 150
#: White paper around the printed pattern, in squares.
PAPER_MARGIN_SQUARES = 1.0


def board_to_world(spec: BoardSpec) -> np.ndarray:
    """(4, 4) board-frame-to-world transform: the board centred on the wall at the origin."""
    width, height = spec.size_m
    pose = np.eye(4)
    pose[:3, 3] = (-width / 2, -height / 2, 0.0)
    return pose


def board_view_poses(count: int, *, distance_m: tuple[float, float] = (0.7, 1.2),
                     tilt_deg: float = 30.0, min_tilt_deg: float = 0.0,
                     roll_deg: float = 15.0, seed: int = 0) -> list[np.ndarray]:
    """Camera-to-world poses looking at the board from varied directions.

    Each view looks at a point within 3 cm of the board's centre from ``distance_m``
    away, tilted off the wall's normal by angles drawn in [-tilt, tilt] about the
    wall's horizontal and vertical axes (at least ``min_tilt_deg`` in total), rolled by
    up to ``roll_deg`` about the viewing direction.

    Returns:
        ``count`` (4, 4) camera-to-world poses.
    """
    rng = np.random.default_rng(seed)
    poses = []
    while len(poses) < count:
        a, b = np.deg2rad(rng.uniform(-tilt_deg, tilt_deg, 2))
        if np.degrees(np.hypot(a, b)) < min_tilt_deg:
            continue
        direction = np.array([np.tan(a), np.tan(b), -1.0])
        direction /= np.linalg.norm(direction)
        target = np.array([*rng.uniform(-0.03, 0.03, 2), 0.0])
        eye = target + rng.uniform(*distance_m) * direction
        roll = np.deg2rad(rng.uniform(-roll_deg, roll_deg))
        up = np.array([np.sin(roll), -np.cos(roll), 0.0])
        poses.append(look_at(eye, target, up))
    return poses


def interpolate_poses(key_times_s: np.ndarray, key_poses: Sequence[np.ndarray],
                      times_s: np.ndarray) -> np.ndarray:
    """(T, 4, 4) poses at ``times_s``: positions linear, rotations slerped between keys."""
    from scipy.spatial.transform import Rotation, Slerp

    key_times_s = np.asarray(key_times_s, dtype=np.float64)
    keys = np.stack(key_poses)
    times = np.clip(np.asarray(times_s, dtype=np.float64), key_times_s[0], key_times_s[-1])
    out = np.tile(np.eye(4), (times.size, 1, 1))
    out[:, :3, :3] = Slerp(key_times_s, Rotation.from_matrix(keys[:, :3, :3]))(times).as_matrix()
    for axis in range(3):
        out[:, axis, 3] = np.interp(times, key_times_s, keys[:, axis, 3])
    return out


def render_board_image(spec: BoardSpec, cam_to_world: np.ndarray, camera: CameraIntrinsics,
                       distortion: Sequence[float] = (), *, supersample: int = 2,
                       pixels_per_square: int = 48, noise_std: float = 2.0,
                       rng: np.random.Generator | None = None) -> np.ndarray:
    """The camera's view of the board on the wall.

    Args:
        spec: the board (its OpenCV texture is what the camera sees).
        cam_to_world: (4, 4) camera pose.
        camera: intrinsics of the rendered image (pixels).
        distortion: OpenCV distortion (k1, k2, p1, p2[, k3]) of the camera, or empty.
        supersample: rendered at this many samples per pixel per side, then averaged.
        pixels_per_square: texture resolution.
        noise_std: Gaussian pixel noise (grey levels).
        rng: noise source (seed 0 when None).

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    import cv2

    rng = rng or np.random.default_rng(0)
    texture = spec.texture(pixels_per_square)
    margin = round(PAPER_MARGIN_SQUARES * pixels_per_square)
    paper = cv2.copyMakeBorder(texture, margin, margin, margin, margin, cv2.BORDER_CONSTANT,
                               value=255)
    ss = int(supersample)
    h, w = camera.height * ss, camera.width * ss
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = (u + 0.5) / ss - 0.5, (v + 0.5) / ss - 0.5
    norm = np.column_stack([(u.ravel() - camera.cx) / camera.fx,
                            (v.ravel() - camera.cy) / camera.fy])
    if len(distortion):
        # Distortion is smooth: undistort a coarse grid (every 4th sample) exactly and
        # interpolate the displacement in between.
        coarse = np.stack([u[::4, ::4], v[::4, ::4]], axis=-1)
        exact = cv2.undistortPoints(coarse.reshape(-1, 1, 2), camera.matrix,
                                    np.asarray(distortion, dtype=np.float64),
                                    criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                              40, 1e-10)).reshape(coarse.shape)
        shift = exact - np.stack([(coarse[..., 0] - camera.cx) / camera.fx,
                                  (coarse[..., 1] - camera.cy) / camera.fy], axis=-1)
        shift = cv2.resize(shift.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        norm = norm + shift.reshape(-1, 2)
    board_pose = np.linalg.inv(cam_to_world) @ board_to_world(spec)  # board -> camera
    rot, trans = board_pose[:3, :3], board_pose[:3, 3]
    # Board-frame ray R^T (x, y, 1), component by component (a (N, 3) @ (3, 3) product
    # is far slower for millions of rows).
    ray = [rot[0, k] * norm[:, 0] + rot[1, k] * norm[:, 1] + rot[2, k] for k in range(3)]
    origin = -rot.T @ trans
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -origin[2] / ray[2]
    ppm = pixels_per_square / spec.square_m
    ahead = s > 0
    map_x = np.where(ahead, (origin[0] + s * ray[0]) * ppm - 0.5 + margin, -1e6)
    map_y = np.where(ahead, (origin[1] + s * ray[1]) * ppm - 0.5 + margin, -1e6)
    map_x, map_y = map_x.astype(np.float32), map_y.astype(np.float32)
    big = cv2.remap(paper, map_x.reshape(h, w), map_y.reshape(h, w), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=WALL_GREY)
    grey = cv2.resize(big.astype(np.float32), (camera.width, camera.height),
                      interpolation=cv2.INTER_AREA)
    grey = np.clip(grey + rng.normal(0.0, noise_std, grey.shape), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


@dataclass(frozen=True)
class SyntheticBoardRecording:
    """What :func:`write_board_recording` wrote (the ground truth).

    Attributes:
        zone_frames: the zone frames (sensor clock).
        image_times_s: colour image stamps (camera clock), seconds.
        zone_poses: (F, 4, 4) camera-to-world poses at the zone frames' true times.
    """

    zone_frames: list[ZoneFrame]
    image_times_s: np.ndarray
    zone_poses: np.ndarray


def write_board_recording(folder: str | os.PathLike, extrinsics: SensorExtrinsics,
                          camera: CameraIntrinsics, spec: BoardSpec,
                          key_poses: Sequence[np.ndarray], *,
                          key_times_s: np.ndarray | None = None,
                          image_times_s: np.ndarray | None = None,
                          zone_times_s: np.ndarray | None = None,
                          time_offset_s: float = 0.0,
                          recorded_intrinsics: CameraIntrinsics | None = None,
                          distortion: Sequence[float] = (),
                          sensor_planes: np.ndarray = WALL, mean_noise_m: float = 0.02,
                          invalid_fraction: float = 0.1, grid: int = 8,
                          fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                          with_depth: bool = False, seed: int = 0) -> SyntheticBoardRecording:
    """Write a recording (colour + zones, no depth unless asked) of a rig viewing the board.

    By default one image and one zone frame per key pose, both at the key's time
    (``0, 1, 2, ...`` s). Pass ``image_times_s`` / ``zone_times_s`` (true times) to move
    the rig continuously between the keys instead.

    Args:
        folder: new recording folder.
        extrinsics: the true sensor-to-camera transform.
        camera: the true camera intrinsics.
        spec: the board.
        key_poses: camera-to-world poses (e.g. :func:`board_view_poses`).
        key_times_s: times of the keys (default 0, 1, 2, ... s).
        image_times_s, zone_times_s: true capture times of images and zone frames.
        time_offset_s: the camera clock runs this far ahead of the sensor's: an image
            taken at true time t is stamped t + offset.
        recorded_intrinsics: intrinsics written to ``meta.json`` (e.g. a rough guess);
            default the true ones.
        distortion: the camera's true distortion (OpenCV order).
        sensor_planes: what the zones see (default the wall; anything else simulates a
            sensor looking past the board's surface).
        mean_noise_m, invalid_fraction: zone noise (metres) and random invalid zones.
        grid, fov_deg: sensor grid and field of view.
        with_depth: also write the camera's true depth (the wall) as ``depth/``.
        seed: random seed.
    """
    from deltar.calibration.synthetic import render_planes_depth
    from deltar.io.recording import RecordingMeta, RecordingWriter

    rng = np.random.default_rng(seed)
    keys = list(key_poses)
    key_t = np.arange(len(keys), dtype=np.float64) if key_times_s is None else \
        np.asarray(key_times_s, dtype=np.float64)
    image_t = key_t if image_times_s is None else np.asarray(image_times_s, dtype=np.float64)
    zone_t = key_t if zone_times_s is None else np.asarray(zone_times_s, dtype=np.float64)
    sensor_cam, rects = sensor_virtual_camera(grid, fov_deg)
    writer = RecordingWriter(folder, RecordingMeta(recorded_intrinsics or camera,
                                                   SYNTHETIC_RIG_SENSOR, grid, fov_deg))
    zone_poses = interpolate_poses(key_t, keys, zone_t)
    frames = []
    for t, pose in zip(zone_t, zone_poses, strict=True):
        frame = simulated_zone_frame(sensor_planes, sensor_pose(pose, extrinsics), sensor_cam,
                                     rects, float(t), rng, mean_noise_m=mean_noise_m,
                                     invalid_fraction=invalid_fraction)
        writer.add_zone_frame(frame)
        frames.append(frame)
    stamps = image_t + float(time_offset_s)
    for stamp, pose in zip(stamps, interpolate_poses(key_t, keys, image_t), strict=True):
        writer.add_color(stamp, render_board_image(spec, pose, camera, distortion, rng=rng))
        if with_depth:
            writer.add_depth(stamp, render_planes_depth(WALL, pose, camera))
    return SyntheticBoardRecording(frames, stamps, zone_poses)
