"""The zone reading model: it predicts the sensor model's zone readings of a plane, and
planes and the extrinsic fitted to it lose the readings' bias on steep views."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.plane import fit_plane_to_zones, zone_cells_tan
from deltar.calibration.synthetic import render_planes_depth, sensor_pose, sensor_virtual_camera
from deltar.calibration.synthetic_board import WALL, board_view_poses
from deltar.calibration.zone_model import (
    ZoneReadingModel,
    refine_extrinsics_to_zones,
    refit_zone_plane,
)
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.simulate_frame import simulate_zone_frame

TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))
SENSOR_CAM, RECTS = sensor_virtual_camera()


def _wall_in(pose: np.ndarray) -> tuple[np.ndarray, float]:
    """The wall in the frame of a device at ``pose`` (device-to-world): normal towards it,
    offset in metres."""
    normal = pose[:3, :3].T @ WALL[0, :3]
    offset = float(WALL[0, :3] @ pose[:3, 3] + WALL[0, 3])
    return (normal, offset) if offset > 0 else (-normal, -offset)


def _readings(sensor_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    depth = render_planes_depth(WALL, sensor_to_world, SENSOR_CAM)
    mean, _, valid = simulate_zone_frame(depth, RECTS).flat()
    return mean.astype(np.float64), valid


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(a @ b), -1.0, 1.0))))


def _steep_views(count: int, seed: int = 0) -> list[np.ndarray]:
    return board_view_poses(count, distance_m=(0.5, 0.9), tilt_deg=45.0, min_tilt_deg=25.0,
                            seed=seed)


@pytest.mark.parametrize(("tilt_deg", "offset_m", "largest_m"),
                         [(0.0, 0.7, 1e-6), (20.0, 0.5, 0.003), (30.0, 0.9, 0.003),
                          (40.0, 0.7, 0.006), (50.0, 0.5, 0.012)])
def test_predicts_the_simulated_reading_of_a_tilted_plane(tilt_deg, offset_m, largest_m):
    tilt = np.deg2rad(tilt_deg)
    normal = np.array([np.sin(tilt) * 0.6, np.sin(tilt) * 0.8, -np.cos(tilt)])
    # The sensor at the origin looking along +z (world = sensor frame).
    depth = render_planes_depth(np.append(normal, offset_m)[None], np.eye(4), SENSOR_CAM)
    measured, _, valid = simulate_zone_frame(depth, RECTS).flat()
    predicted, predicted_valid = ZoneReadingModel().predict(normal, offset_m)
    assert np.array_equal(valid, predicted_valid)
    error = (predicted - measured)[valid]
    assert np.sqrt(np.mean(error ** 2)) < 0.002
    assert np.max(np.abs(error)) < largest_m
    if tilt_deg > 0:
        # The plane's depth at the zones' centre rays is farther off.
        cells = zone_cells_tan(8)
        u, v = (cells[:, 1] + cells[:, 3]) / 2, (cells[:, 0] + cells[:, 2]) / 2
        at_centre = (-offset_m / (normal[0] * u + normal[1] * v + normal[2]) - measured)[valid]
        assert np.sqrt(np.mean(at_centre ** 2)) > 1.4 * np.sqrt(np.mean(error ** 2))


def test_batched_prediction_matches_single_planes_and_planes_behind_are_empty():
    model = ZoneReadingModel()
    normals = np.array([[0.3, -0.2, -0.93], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = np.array([0.8, 1.3, 0.5])
    means, valid = model.predict(normals, offsets)
    assert means.shape == valid.shape == (3, 64)
    for k in range(2):
        single_mean, single_valid = model.predict(normals[k], offsets[k])
        np.testing.assert_allclose(means[k], single_mean)
        assert np.array_equal(valid[k], single_valid)
        assert valid[k].all()
    assert not valid[2].any() and np.all(means[2] == 0)  # the plane is behind the sensor
    # Head-on at 1.30 m: every zone sees one bin (1.28-1.32 m) and reports its centre.
    np.testing.assert_allclose(means[1], 1.30, atol=1e-9)


def test_model_validates_its_input():
    with pytest.raises(ValueError, match="grid"):
        ZoneReadingModel(grid=5)
    with pytest.raises(ValueError, match="offsets_m"):
        ZoneReadingModel().predict(np.array([[0.0, 0.0, -1.0]]), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="one entry per view"):
        refine_extrinsics_to_zones([(np.array([0.0, 0.0, -1.0]), 1.0)], [], [], TRUE)


def test_refitted_planes_of_steep_views_lose_the_em_fits_bias():
    em_errors, refit_errors = [], []
    for pose in _steep_views(12):
        sensor = sensor_pose(pose, TRUE)
        normal, offset = _wall_in(sensor)
        mean, valid = _readings(sensor)
        em = fit_plane_to_zones(mean, valid)
        refit = refit_zone_plane(em, mean)
        assert np.array_equal(refit.inliers, em.inliers)
        assert refit.rms_residual_m < 0.004
        em_errors.append(_angle_deg(em.normal, normal))
        refit_errors.append(_angle_deg(refit.normal, normal))
        assert abs(refit.offset_m - offset) < 0.002
    assert np.mean(refit_errors) < 0.6 * np.mean(em_errors)
    assert np.max(refit_errors) < 0.2 < np.max(em_errors)


def test_noise_free_steep_views_give_the_extrinsic_within_0_05_deg():
    poses = _steep_views(20, seed=2)
    planes, means, masks = [], [], []
    for pose in poses:
        mean, valid = _readings(sensor_pose(pose, TRUE))
        planes.append(_wall_in(pose))
        means.append(mean)
        masks.append(valid)
    turn = Rotation.from_euler("xyz", [0.5, -0.4, 0.6], degrees=True).as_matrix()
    shift = np.array([0.004, -0.003, 0.005])
    start = SensorExtrinsics(turn @ TRUE.rotation, TRUE.translation_m + shift)
    refined = refine_extrinsics_to_zones(planes, means, masks, start)
    angle = np.degrees(Rotation.from_matrix(refined.extrinsics.rotation @ TRUE.rotation.T)
                       .magnitude())
    assert angle < 0.05
    assert np.linalg.norm(refined.extrinsics.translation_m - TRUE.translation_m) < 0.001
    assert refined.rms_residual_m < 0.002
    assert refined.zones == sum(int(m.sum()) for m in masks)


def test_refinement_with_zone_noise_stays_near_the_truth():
    rng = np.random.default_rng(4)
    planes, means, masks = [], [], []
    for pose in _steep_views(20, seed=3):
        mean, valid = _readings(sensor_pose(pose, TRUE))
        valid = valid & (rng.random(valid.size) >= 0.1)
        planes.append(_wall_in(pose))
        means.append(mean + rng.normal(0.0, 0.02, mean.size))
        masks.append(valid)
    refined = refine_extrinsics_to_zones(planes, means, masks, TRUE)
    angle = np.degrees(Rotation.from_matrix(refined.extrinsics.rotation @ TRUE.rotation.T)
                       .magnitude())
    # The Cramer-Rao bound of such views is about 0.26 deg rms (benchmarks/RESULTS.md).
    assert angle < 0.8
    assert 0.015 < refined.zone_noise_m < 0.025
