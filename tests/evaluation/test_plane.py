"""Plane fit and flat-wall metrics on synthetic walls with noise and outliers."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.camera import CameraIntrinsics, backproject
from deltar.evaluation.plane import Plane, fit_plane, pixel_rays, plane_metrics

K = CameraIntrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)


def wall_depth(normal: np.ndarray, offset: float) -> np.ndarray:
    """Exact depth map (48, 64) of the plane n . p + d = 0, computed ray by ray."""
    normal = normal / np.linalg.norm(normal)
    depth = np.zeros((K.height, K.width))
    for v in range(K.height):
        for u in range(K.width):
            ray = np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
            depth[v, u] = -offset / (normal @ ray)
    return depth


TILTED = np.array([0.2, -0.1, -1.0])


def test_backproject_recovers_pixel_coordinates() -> None:
    depth = np.full((48, 64), 2.0)
    depth[0, 0] = 0.0  # invalid
    points = backproject(depth, K)
    assert points.shape == (48 * 64 - 1, 3)
    u = points[:, 0] / points[:, 2] * K.fx + K.cx
    v = points[:, 1] / points[:, 2] * K.fy + K.cy
    np.testing.assert_allclose(u[:3], [1, 2, 3])
    np.testing.assert_allclose(v[:2], [0, 0])
    np.testing.assert_allclose(points[:, 2], 2.0)


def test_fit_plane_exact() -> None:
    depth = wall_depth(TILTED, 2.0)
    plane, inliers = fit_plane(backproject(depth, K))
    # The wall was built with a positive offset, so its normal keeps its orientation
    # (pointing back towards the camera).
    expected = TILTED / np.linalg.norm(TILTED)
    np.testing.assert_allclose(plane.normal, expected, atol=1e-6)
    assert plane.offset == pytest.approx(2.0, abs=1e-6)
    assert inliers.all()


def test_fit_plane_ignores_outliers() -> None:
    rng = np.random.default_rng(0)
    depth = wall_depth(TILTED, 2.0) + rng.normal(0, 0.005, (48, 64))
    outliers = rng.random((48, 64)) < 0.3
    depth[outliers] = rng.uniform(0.5, 4.0, outliers.sum())
    plane, inliers = fit_plane(backproject(depth, K))
    expected = TILTED / np.linalg.norm(TILTED)
    assert np.degrees(np.arccos(min(1.0, plane.normal @ expected))) < 1.0
    assert plane.offset == pytest.approx(2.0, abs=0.01)
    # Nearly all true outliers rejected, nearly all wall points kept.
    flat_outliers = outliers.reshape(-1)
    assert inliers[flat_outliers].mean() < 0.05
    assert inliers[~flat_outliers].mean() > 0.95


def test_plane_metrics_bias_and_jitter_against_ground_truth_plane() -> None:
    rng = np.random.default_rng(1)
    gt = wall_depth(TILTED, 2.0)
    plane, _ = fit_plane(backproject(gt, K))
    noise = rng.normal(0.03, 0.01, gt.shape)  # 3 cm behind the wall, 1 cm jitter
    metrics = plane_metrics(gt + noise, K, plane=plane)
    assert metrics.mean_error_m == pytest.approx(noise.mean(), abs=1e-3)
    assert metrics.jitter_m == pytest.approx(noise.std(), rel=0.05)
    assert metrics.bias_m == pytest.approx(np.abs(noise).mean(), abs=1e-3)
    assert metrics.num_points == 48 * 64
    assert metrics.inlier_fraction > 0.99


def test_plane_metrics_self_fit_measures_jitter_only() -> None:
    rng = np.random.default_rng(2)
    noise = rng.normal(0.0, 0.01, (48, 64))
    depth = wall_depth(TILTED, 2.5) + noise
    depth[:4, :4] = 0.0  # invalid pixels are skipped
    metrics = plane_metrics(depth, K)
    valid_noise = noise[depth > 0]
    assert metrics.jitter_m == pytest.approx(valid_noise.std(), rel=0.1)
    assert metrics.bias_m == pytest.approx(np.abs(valid_noise).mean(), rel=0.1)
    assert metrics.num_points == 48 * 64 - 16


def test_plane_metrics_with_mask_and_outliers() -> None:
    rng = np.random.default_rng(3)
    depth = wall_depth(TILTED, 2.0) + rng.normal(0.0, 0.002, (48, 64))
    depth[10:20, 10:20] = 0.5  # an object in front of the wall
    mask = np.ones((48, 64), bool)
    mask[:, :5] = False
    metrics = plane_metrics(depth, K, mask=mask)
    assert metrics.num_points == 48 * 59
    assert metrics.bias_m < 0.005 and metrics.jitter_m < 0.005
    assert metrics.inlier_fraction == pytest.approx(1 - 100 / (48 * 59), abs=0.01)
    assert set(metrics.to_dict()) >= {"bias_m", "jitter_m", "plane_normal"}


def test_depth_along_rays_inverts_backprojection() -> None:
    plane = Plane(np.array([0.0, 0.0, -1.0]), 3.0)  # z = 3
    rays = pixel_rays(2, 3, K).reshape(-1, 3)
    np.testing.assert_allclose(plane.depth_along_rays(rays), 3.0)


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="NaN"):
        plane_metrics(np.full((48, 64), np.nan), K)
    with pytest.raises(ValueError, match="intrinsics"):
        plane_metrics(np.ones((10, 10)), K)
    with pytest.raises(ValueError, match="valid pixels"):
        plane_metrics(np.zeros((48, 64)), K)
    with pytest.raises(ValueError, match="at least 3"):
        fit_plane(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="degenerate"):
        fit_plane(np.tile([[1.0, 2.0, 3.0]], (10, 1)))
    with pytest.raises(ValueError, match="mask"):
        plane_metrics(np.ones((48, 64)), K, mask=np.ones((4, 4), bool))
