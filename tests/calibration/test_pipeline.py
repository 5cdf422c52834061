"""Calibration on real scene geometry: the 7-Scenes kitchen as the world.

Ten real depth frames of ../shared are fused with their poses into a world point cloud;
three non-parallel planes among its six largest (by RANSAC) are the targets. A virtual rig with a
known extrinsic is placed in front of them; camera depth and the sensor's view are
re-rendered from the real points (z-buffer), the zones simulated with the sensor
simulator plus 2 cm noise and 10% invalid zones, then calibrated. Real surfaces are not
perfect planes and carry clutter, so this is harder than the box room: with seeds 0-2
the measured errors were 0.33-0.78 deg and 3.1-6.5 mm (tolerances below: 1 deg, 1 cm).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.extrinsic import depth_to_points, nominal_extrinsics
from deltar.calibration.pipeline import calibrate_observations, observation_from_frame
from deltar.calibration.plane import ransac_plane
from deltar.calibration.slam import world_to_camera
from deltar.calibration.synthetic import (
    look_at,
    render_points_depth,
    sensor_pose,
    sensor_virtual_camera,
)
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.simulate import simulate_zone_frame
from deltar.sensor.zone_frame import ZoneFrame

KINECT = CameraIntrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)  # camera-intrinsics.txt
CAMERA = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)  # the virtual rig's camera
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))


def _kitchen_world(folder) -> tuple[np.ndarray, np.ndarray]:
    """World points (1 cm voxels) fused from 10 frames, and the mean camera centre."""
    clouds, centres = [], []
    for index in range(0, 1000, 100):
        depth = cv2.imread(str(folder / f"frame-{index:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
        assert depth is not None, f"missing frame {index}"
        depth = depth.astype(np.float32)
        depth[depth >= 65535] = 0  # 65535 marks invalid depth in 7-Scenes
        pose = np.loadtxt(folder / f"frame-{index:06d}.pose.txt")  # camera-to-world
        points = depth_to_points(depth / 1000.0, KINECT, stride=2)
        clouds.append(points @ pose[:3, :3].T + pose[:3, 3])
        centres.append(pose[:3, 3])
    world = np.concatenate(clouds)
    voxel = np.floor(world / 0.01).astype(np.int64)
    voxel -= voxel.min(axis=0)
    key = (voxel[:, 0] * (voxel[:, 1].max() + 1) + voxel[:, 1]) * (voxel[:, 2].max() + 1) + \
        voxel[:, 2]
    _, keep = np.unique(key, return_index=True)
    return world[keep], np.mean(centres, axis=0)


def test_calibration_on_the_real_kitchen_geometry(shared_data):
    world, viewer = _kitchen_world(shared_data / "7scenes_redkitchen")
    rng = np.random.default_rng(0)
    remaining, planes = world, []
    for k in range(6):
        sample = remaining[rng.choice(len(remaining), 20000, replace=False)]
        normal, offset, _ = ransac_plane(sample, 0.015, iterations=512, seed=k)
        on_plane = np.abs(remaining @ normal + offset) < 0.015
        if normal @ viewer + offset < 0:  # face the side the real camera was on
            normal, offset = -normal, -offset
        planes.append((normal, remaining[on_plane]))
        remaining = remaining[~on_plane]
    normals = np.array([n for n, _ in planes])
    # Keep the first three mutually non-parallel planes as targets.
    targets = [0]
    for k in range(1, len(planes)):
        if len(targets) < 3 and all(abs(normals[k] @ normals[j]) < 0.9 for j in targets):
            targets.append(k)
    assert len(targets) == 3

    sensor_cam, rects = sensor_virtual_camera(8, (45.0, 45.0), 16)
    nominal = nominal_extrinsics(90.0)
    observations, skipped = [], 0
    for k in targets:
        normal, points = planes[k]
        tangent_a = np.cross(normal, [0.3, 0.5, 0.8])
        tangent_a /= np.linalg.norm(tangent_a)
        tangents = np.stack([tangent_a, np.cross(normal, tangent_a)])
        for j in range(12):
            target = points[rng.integers(len(points))]
            direction = normal + np.tan(np.radians(40)) * rng.uniform(-1, 1, 2) @ tangents
            eye = target + direction / np.linalg.norm(direction)  # 1 m from the target
            pose = look_at(eye, target, (0, 0, 1.0) if abs(normal[1]) > 0.7 else (0, -1.0, 0))
            depth = render_points_depth(world_to_camera(world, pose), CAMERA)
            sensor_depth = render_points_depth(
                world_to_camera(world, sensor_pose(pose, TRUE)), sensor_cam)
            clean = simulate_zone_frame(sensor_depth, rects)
            mean, sigma, valid = clean.flat()
            valid = valid & (rng.random(64) >= 0.1)
            noisy = np.clip(mean + rng.normal(0, 0.02, 64), 1e-3, None)
            frame = ZoneFrame(np.where(valid, noisy, 0), np.where(valid, sigma, 0), valid)
            try:
                observations.append(observation_from_frame(
                    frame, depth_to_points(depth, CAMERA, 2), nominal, name=f"{k}-{j}"))
            except ValueError:
                skipped += 1  # cluttered or grazing views are refused, as on a real rig
    assert len(observations) >= 15, f"only {len(observations)} usable frames"
    result = calibrate_observations(observations, nominal, CAMERA)
    solved = result.calibration.extrinsics
    error_deg = np.degrees(Rotation.from_matrix(solved.rotation @ TRUE.rotation.T).magnitude())
    assert error_deg < 1.0
    assert np.linalg.norm(solved.translation_m - TRUE.translation_m) < 0.01
    assert result.distance_after_m < result.distance_before_m


def test_whole_cluttered_kitchen_frames_are_refused_not_misfitted(shared_data):
    """The kitchen's own frames (a general scan, not a calibration recording) mostly show
    clutter; the pipeline must refuse them with advice rather than return a pose."""
    folder = shared_data / "7scenes_redkitchen"
    sensor_cam, rects = sensor_virtual_camera(8, (45.0, 45.0), 16)
    nominal = nominal_extrinsics(90.0)
    observations, reasons = [], []
    for path in sorted(folder.glob("frame-*.depth.png"))[::40]:
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float32)
        depth[depth >= 65535] = 0
        points = depth_to_points(depth / 1000.0, KINECT)
        sensor_points = (points - TRUE.translation_m) @ TRUE.rotation  # camera -> sensor
        frame = simulate_zone_frame(render_points_depth(sensor_points, sensor_cam), rects)
        try:
            observations.append(observation_from_frame(frame, points[::16], nominal,
                                                       name=path.name))
        except ValueError as err:
            reasons.append(str(err))
    assert len(reasons) > len(observations)
    assert any("fill the sensor's view with a flat surface" in r for r in reasons)
    with pytest.raises(ValueError, match="record at least three planes"):
        calibrate_observations(observations, nominal, KINECT)
