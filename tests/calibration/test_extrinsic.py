"""Extrinsic calibration (DELTAR Eq. 2) on a synthetic rig with a known answer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.extrinsic import (
    check_plane_diversity,
    depth_to_points,
    nominal_extrinsics,
    points_in_sensor_view,
)
from deltar.calibration.pipeline import calibrate_observations, observation_from_frame
from deltar.calibration.synthetic import synthetic_rig_frames
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import SensorExtrinsics

CAMERA = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
# Same viewing direction, rolled 91.5 deg, tilted 2 and -1.5 deg, a few cm apart.
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))


def _rotation_error_deg(a: SensorExtrinsics, b: SensorExtrinsics) -> float:
    return float(np.degrees(Rotation.from_matrix(a.rotation @ b.rotation.T).magnitude()))


def _observations(frames, nominal):
    return [observation_from_frame(f.zone_frame, depth_to_points(f.depth_m, CAMERA, 2), nominal,
                                   name=str(f.zone_frame.timestamp_s)) for f in frames]


def test_nominal_extrinsics_is_a_roll_about_the_optical_axis():
    ext = nominal_extrinsics(90.0, (0.01, 0.0, 0.0))
    # Sensor x (zone columns) maps onto camera y: rolled a quarter turn.
    np.testing.assert_allclose(ext.rotation @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-12)
    np.testing.assert_allclose(ext.rotation @ [0, 0, 1.0], [0, 0, 1.0], atol=1e-12)
    np.testing.assert_allclose(ext.translation_m, [0.01, 0, 0])


def test_synthetic_room_recovers_rotation_and_translation():
    """Six planes of a room, 4 noisy frames each (2 cm zone noise, 10% invalid zones)."""
    frames = synthetic_rig_frames(TRUE, CAMERA, frames_per_plane=4, mean_noise_m=0.02,
                                  invalid_fraction=0.1, seed=0)
    nominal = nominal_extrinsics(90.0)
    result = calibrate_observations(_observations(frames, nominal), nominal, CAMERA)
    solved = result.calibration.extrinsics
    assert _rotation_error_deg(solved, TRUE) < 0.5
    assert np.linalg.norm(solved.translation_m - TRUE.translation_m) < 0.01
    # The nominal guess is 2.9 deg and 4.6 cm off; the zones must move closer to the cloud.
    assert result.distance_after_m < result.distance_before_m
    assert result.calibration.residuals["frames_used"] == 24


def test_three_planes_are_enough():
    frames = synthetic_rig_frames(TRUE, CAMERA, view_planes=(0, 2, 4), frames_per_plane=4,
                                  mean_noise_m=0.01, seed=1)
    nominal = nominal_extrinsics(88.0)
    result = calibrate_observations(_observations(frames, nominal), nominal, CAMERA)
    assert _rotation_error_deg(result.calibration.extrinsics, TRUE) < 0.5
    assert np.linalg.norm(result.calibration.extrinsics.translation_m - TRUE.translation_m) < 0.01


def test_one_plane_viewed_at_many_angles_is_enough():
    """What fixes R and t is the spread of plane orientations seen from the sensor, so a
    single wall viewed at up to ~25 degrees off-normal works too."""
    frames = synthetic_rig_frames(TRUE, CAMERA, view_planes=(0,), frames_per_plane=16,
                                  mean_noise_m=0.01, seed=3)
    nominal = nominal_extrinsics(90.0)
    result = calibrate_observations(_observations(frames, nominal), nominal, CAMERA)
    assert _rotation_error_deg(result.calibration.extrinsics, TRUE) < 0.5
    assert np.linalg.norm(result.calibration.extrinsics.translation_m - TRUE.translation_m) < 0.01


@pytest.mark.parametrize("view_planes", [(0,), (0, 1), (0, 2, 4)])
def test_head_on_scans_say_what_to_record(view_planes):
    """Facing planes head-on gives one normal in the sensor frame however many planes."""
    frames = synthetic_rig_frames(TRUE, CAMERA, view_planes=view_planes, frames_per_plane=3,
                                  tilt_deg=2.0, mean_noise_m=0.0, seed=2)
    nominal = nominal_extrinsics(90.0)
    with pytest.raises(ValueError, match="all planes are parallel as seen from the sensor: "
                                         "record at least three planes"):
        calibrate_observations(_observations(frames, nominal), nominal, CAMERA)


def test_plane_diversity_check():
    with pytest.raises(ValueError, match="only 2 usable plane frames"):
        check_plane_diversity(np.eye(3)[:2])
    check_plane_diversity(np.eye(3))  # three orthogonal planes are fine
    rng = np.random.default_rng(0)
    # Normals tilted about the y axis only (the rig panned left-right): one axis is free.
    angles = rng.uniform(-0.5, 0.5, 12)
    panned = np.column_stack([np.sin(angles), np.zeros(12), -np.cos(angles)])
    with pytest.raises(ValueError, match="lie in one plane as seen from the sensor"):
        check_plane_diversity(panned)


def test_points_in_sensor_view_uses_the_field_of_view():
    ext = SensorExtrinsics()
    tan = np.tan(np.radians(22.5))
    pts = np.array([[0, 0, 1.0], [0.99 * tan, 0, 1.0], [1.01 * tan, 0, 1.0], [0, 0, -1.0]])
    np.testing.assert_array_equal(points_in_sensor_view(pts, ext), [True, True, False, False])
    # A point hidden 1 m behind a nearer one in the same direction is dropped.
    hidden = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]])
    np.testing.assert_array_equal(points_in_sensor_view(hidden, ext, visible_only=True),
                                  [True, False])


def test_depth_to_points_back_projects_with_the_intrinsics():
    depth = np.zeros((120, 160), np.float32)
    depth[59, 79] = 2.0  # one pixel, next to the principal point (79.5, 59.5)
    pts = depth_to_points(depth, CAMERA)
    np.testing.assert_allclose(pts, [[-0.5 / 150 * 2, -0.5 / 150 * 2, 2.0]])
    with pytest.raises(ValueError, match="intrinsics are for"):
        depth_to_points(np.ones((10, 10)), CAMERA)
