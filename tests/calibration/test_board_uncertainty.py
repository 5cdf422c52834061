"""The board calibration's expected error: the footprint model, the Cramer-Rao bound
against the scatter of a maximum-likelihood solve, and what the view geometry does."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from deltar.calibration.board_uncertainty import (
    extrinsic_uncertainty,
    predicted_zone_depth,
    zone_footprint_rays,
)
from deltar.calibration.synthetic import (
    render_planes_depth,
    sensor_pose,
    sensor_virtual_camera,
)
from deltar.calibration.synthetic_board import WALL, board_view_poses
from deltar.sensor.geometry import SensorExtrinsics

TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))
RAYS = zone_footprint_rays()


def _wall_planes(poses):
    """The wall in each camera's frame: (normal towards the camera, offset, 0, 0)."""
    return [(pose[:3, :3].T @ WALL[0, :3], float(WALL[0, :3] @ pose[:3, 3]), 0.0, 0.0)
            for pose in poses]


def _poses(views, tilt=(45.0, 25.0), seed=0):
    return board_view_poses(views, distance_m=(0.5, 0.9), tilt_deg=tilt[0],
                            min_tilt_deg=tilt[1], seed=seed)


def test_footprint_model_is_the_mean_of_the_rendered_depth():
    pose = _poses(1, seed=3)[0]
    normal, offset, _, _ = _wall_planes([pose])[0]
    predicted = predicted_zone_depth(normal, offset, TRUE, RAYS)
    camera, rects = sensor_virtual_camera(pixels_per_zone=32)
    depth = render_planes_depth(WALL, sensor_pose(pose, TRUE), camera)
    rendered = np.array([depth[y0:y1, x0:x1].mean()
                         for y0, x0, y1, x1 in np.ceil(rects).astype(int)])
    # Within the rendering's pixel steps; the zones' centre rays alone are off by more
    # on this tilted wall.
    centre = predicted_zone_depth(normal, offset, TRUE, zone_footprint_rays(samples=1))
    error = np.abs(predicted - rendered).max()
    assert error < 0.002 and error < 0.5 * np.abs(centre - rendered).max()
    head_on = predicted_zone_depth(np.array([0.0, 0.0, -1.0]), 1.0, SensorExtrinsics(
        np.eye(3), np.zeros(3)), RAYS)
    np.testing.assert_allclose(head_on, 1.0)


def test_bound_matches_the_scatter_of_a_maximum_likelihood_solve():
    """Zones drawn from the footprint model with 1 cm noise, solved by least squares 40
    times: the rotation and translation scatter is the bound's within sampling error."""
    poses = _poses(8, seed=1)
    planes = _wall_planes(poses)
    clean = [predicted_zone_depth(n, d, TRUE, RAYS) for n, d, _, _ in planes]
    masks = [np.ones(64, dtype=bool)] * len(planes)
    bound = extrinsic_uncertainty(planes, clean, masks, TRUE, zone_noise_m=0.01)
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(40):
        noisy = np.concatenate(clean) + rng.normal(0.0, 0.01, 64 * len(planes))

        def residuals(x, noisy=noisy):
            moved = SensorExtrinsics(Rotation.from_rotvec(x[:3]).as_matrix() @ TRUE.rotation,
                                     TRUE.translation_m + x[3:])
            return np.concatenate([predicted_zone_depth(n, d, moved, RAYS)
                                   for n, d, _, _ in planes]) - noisy

        errors.append(least_squares(residuals, np.zeros(6)).x)
    errors = np.array(errors)
    rotation_rms = np.degrees(np.sqrt(np.mean(np.sum(errors[:, :3] ** 2, axis=1))))
    translation_rms = np.sqrt(np.mean(np.sum(errors[:, 3:] ** 2, axis=1)))
    assert rotation_rms == pytest.approx(bound.rotation_rms_deg, rel=0.25)
    assert translation_rms == pytest.approx(bound.translation_rms_m, rel=0.25)
    # The noise estimated from residuals of the true extrinsic is the noise drawn.
    estimated = extrinsic_uncertainty(planes, np.split(noisy, len(planes)), masks, TRUE)
    assert estimated.zone_noise_m == pytest.approx(0.01, rel=0.15)


def _bound(poses, noise=0.02, normal_sd=0.0):
    """The bound with every zone on the wall (90 % valid, at random)."""
    rng = np.random.default_rng(0)
    planes = [(n, d, normal_sd, 0.0) for n, d, _, _ in _wall_planes(poses)]
    return extrinsic_uncertainty(planes, [predicted_zone_depth(n, d, TRUE, RAYS)
                                          for n, d, _, _ in planes],
                                 [rng.random(64) > 0.1 for _ in planes], TRUE,
                                 zone_noise_m=noise)


def test_steeper_views_pin_the_roll_down():
    """The roll about the viewing axis is the worst-determined rotation; at 15 views the
    guide's 25-45 deg tilts bring the expected error under what 15-35 deg leaves."""
    shallow = _bound(_poses(15, tilt=(35.0, 15.0)))
    steep = _bound(_poses(15, tilt=(45.0, 25.0)))
    assert np.argmax(shallow.rotation_sd_deg) == 2
    assert shallow.rotation_rms_deg > 0.35 > steep.rotation_rms_deg
    assert steep.miss_probability(0.5, 0.010) < 0.5 * shallow.miss_probability(0.5, 0.010)
    more = _bound(_poses(25, tilt=(35.0, 15.0)))
    assert more.rotation_rms_deg < shallow.rotation_rms_deg
    # Uncertain board planes add to the bound.
    assert _bound(_poses(15), normal_sd=0.01).rotation_rms_deg > steep.rotation_rms_deg


def test_a_shared_camera_error_moves_the_solution_with_it():
    """Every board plane turned by the same small angle about the camera's axis (as an
    error in the camera parameters would): the solution turns with it, so the bound grows
    by that angle's variance along (rotation about z, z x t)."""
    poses = _poses(10, seed=2)
    planes = _wall_planes(poses)
    means = [predicted_zone_depth(n, d, TRUE, RAYS) for n, d, _, _ in planes]
    masks = [np.ones(64, dtype=bool)] * len(planes)
    z = np.array([0.0, 0.0, 1.0])
    turning = [np.append(np.cross(z, n), 0.0)[:, None] for n, _, _, _ in planes]  # (4, 1)
    alone = extrinsic_uncertainty(planes, means, masks, TRUE, zone_noise_m=0.02)
    sd = np.deg2rad(0.3)
    shared = extrinsic_uncertainty(planes, means, masks, TRUE, zone_noise_m=0.02,
                                   plane_sensitivity=turning,
                                   camera_covariance=np.array([[sd ** 2]]))
    follow = np.concatenate([z, np.cross(z, TRUE.translation_m)])
    np.testing.assert_allclose(shared.covariance - alone.covariance,
                               sd ** 2 * np.outer(follow, follow), atol=1e-3 * sd ** 2)
    assert shared.rotation_sd_deg[2] == pytest.approx(np.hypot(alone.rotation_sd_deg[2], 0.3),
                                                      rel=1e-3)


def test_bad_input_is_refused():
    poses = _poses(3)
    planes = _wall_planes(poses)
    with pytest.raises(ValueError, match="one entry per view"):
        extrinsic_uncertainty(planes, [np.ones(64)] * 2, [np.ones(64, bool)] * 3, TRUE)
    with pytest.raises(ValueError, match="plane_sensitivity must have one entry per view"):
        extrinsic_uncertainty(planes, [np.ones(64)] * 3, [np.ones(64, bool)] * 3, TRUE,
                              plane_sensitivity=[np.zeros((4, 4))])
    one = [planes[0]] * 3
    with pytest.raises(ValueError, match="undetermined"):
        extrinsic_uncertainty(one, [np.ones(64)] * 3, [np.ones(64, bool)] * 3, TRUE,
                              zone_noise_m=0.02)
