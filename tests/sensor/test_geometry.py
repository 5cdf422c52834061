"""Tests of zone geometry (deltar.sensor.geometry)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics
from deltar.sensor import SensorExtrinsics, zone_angles_deg, zone_rects, zone_rects_to_pixel_bounds
from deltar.sensor.geometry import mirror_zone_rects

K = ZJU_L5_INTRINSICS
HALF_FOV = math.radians(22.5)


def test_identity_rects_are_symmetric_about_the_principal_point():
    raw = zone_rects(K, grid=8)
    assert raw.shape == (64, 4) and raw.dtype == np.float32
    rects = raw.astype(np.float64)
    # Overall extent: cx +- fx tan(22.5 deg), cy +- fy tan(22.5 deg).
    assert rects[:, 1].min() == pytest.approx(K.cx - K.fx * math.tan(HALF_FOV), abs=1e-3)
    assert rects[:, 3].max() == pytest.approx(K.cx + K.fx * math.tan(HALF_FOV), abs=1e-3)
    assert rects[:, 0].min() == pytest.approx(K.cy - K.fy * math.tan(HALF_FOV), abs=1e-3)
    assert rects[:, 2].max() == pytest.approx(K.cy + K.fy * math.tan(HALF_FOV), abs=1e-3)
    grid = rects.reshape(8, 8, 4)
    mirrored_lr = grid[:, ::-1]
    np.testing.assert_allclose(grid[..., 1] - K.cx, -(mirrored_lr[..., 3] - K.cx), atol=1e-3)
    mirrored_ud = grid[::-1]
    np.testing.assert_allclose(grid[..., 0] - K.cy, -(mirrored_ud[..., 2] - K.cy), atol=1e-3)


def test_zone_sizes_for_the_zju_camera():
    rects = zone_rects(K, grid=8).astype(np.float64)
    widths = rects[:, 3] - rects[:, 1]
    heights = rects[:, 2] - rects[:, 0]
    # Column c spans angles [-22.5 + 5.625 c, -22.5 + 5.625 (c + 1)] degrees.
    edges = np.radians(np.linspace(-22.5, 22.5, 9))
    expected = K.fx * (np.tan(edges[1:]) - np.tan(edges[:-1]))
    np.testing.assert_allclose(widths.reshape(8, 8), np.tile(expected, (8, 1)), atol=1e-3)
    assert widths.mean() == pytest.approx(2 * K.fx * math.tan(HALF_FOV) / 8, abs=1e-3)  # 63.3
    assert 58 < widths.min() and widths.max() < 70
    assert 58 < heights.min() and heights.max() < 70
    # Row-major order: zone 1 is right of zone 0, zone 8 below it.
    assert rects[1, 1] == pytest.approx(rects[0, 3], abs=1e-4)
    assert rects[8, 0] == pytest.approx(rects[0, 2], abs=1e-4)


def test_no_translation_means_no_parallax():
    near = zone_rects(K, depth_m=0.5)
    far = zone_rects(K, depth_m=4.0)
    np.testing.assert_allclose(near, far, atol=1e-3)


def test_parallax_shrinks_with_depth():
    baseline = 0.05  # sensor 5 cm along the camera's x axis
    ext = SensorExtrinsics(translation_m=np.array([baseline, 0.0, 0.0]))
    reference = zone_rects(K)
    shifts = []
    for depth in (0.5, 1.0, 2.0, 4.0):
        shift = zone_rects(K, extrinsics=ext, depth_m=depth) - reference
        np.testing.assert_allclose(shift[:, [1, 3]], K.fx * baseline / depth, atol=1e-3)
        np.testing.assert_allclose(shift[:, [0, 2]], 0.0, atol=1e-3)
        shifts.append(shift[0, 1])
    assert np.all(np.diff(shifts) < 0)


def test_per_zone_depth():
    ext = SensorExtrinsics(translation_m=np.array([0.0, 0.03, 0.0]))
    depth = np.linspace(0.5, 3.0, 64)
    rects = zone_rects(K, extrinsics=ext, depth_m=depth)
    shift = rects - zone_rects(K)
    np.testing.assert_allclose(shift[:, 0], K.fy * 0.03 / depth, atol=1e-3)


def test_upside_down_sensor_reverses_the_zone_order():
    flipped = SensorExtrinsics(rotation=np.diag([-1.0, -1.0, 1.0]))
    camera = CameraIntrinsics(600.0, 600.0, 320.0, 240.0, 640, 480)  # centred principal point
    rects = zone_rects(camera, extrinsics=flipped)
    upright = zone_rects(camera)
    # Zone 0 of the rotated sensor covers what zone 63 covers upright.
    np.testing.assert_allclose(rects, upright[::-1], atol=1e-3)


def test_four_by_four_grid_covers_the_same_field():
    rects4 = zone_rects(K, grid=4).reshape(4, 4, 4)
    rects8 = zone_rects(K, grid=8).reshape(8, 8, 4)
    assert zone_angles_deg(4).shape == (16, 4)
    np.testing.assert_allclose(rects4[..., 0], rects8[::2, ::2, 0], atol=1e-3)
    np.testing.assert_allclose(rects4[..., 1], rects8[::2, ::2, 1], atol=1e-3)
    np.testing.assert_allclose(rects4[..., 2], rects8[1::2, 1::2, 2], atol=1e-3)
    np.testing.assert_allclose(rects4[..., 3], rects8[1::2, 1::2, 3], atol=1e-3)


def test_bad_geometry_raises():
    with pytest.raises(ValueError, match="depth_m"):
        zone_rects(K, depth_m=0.0)
    with pytest.raises(ValueError, match="grid"):
        zone_rects(K, grid=0)
    with pytest.raises(ValueError, match="fov_deg"):
        zone_rects(K, fov_deg=(200.0, 45.0))
    with pytest.raises(ValueError, match="rotation"):
        SensorExtrinsics(rotation=np.ones((3, 3)))
    with pytest.raises(ValueError, match="translation_m"):
        SensorExtrinsics(translation_m=np.array([0.0, np.nan, 0.0]))
    behind = SensorExtrinsics(translation_m=np.array([0.0, 0.0, -5.0]))
    with pytest.raises(ValueError, match="behind"):
        zone_rects(K, extrinsics=behind, depth_m=1.0)


def test_a_rotation_written_with_four_decimals_is_made_exact_and_a_scaled_one_refused():
    written = np.array([[0.866, 0.0, 0.5], [0.0, 1.0, 0.0], [-0.5, 0.0, 0.866]])  # 30 deg yaw
    rotation = SensorExtrinsics(rotation=written).rotation
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(rotation, written, atol=1e-4)
    with pytest.raises(ValueError, match=r"SensorExtrinsics.rotation is not a rotation "
                       r"\(\|R\^T R - I\| = 0.21, det = 1.3310; at most 0.001 off"):
        SensorExtrinsics(rotation=np.eye(3) * 1.1)
    with pytest.raises(ValueError, match=r"det = -1\.0000"):
        SensorExtrinsics(rotation=np.diag([1.0, 1.0, -1.0]))  # a reflection


def test_extrinsics_inverse_round_trip():
    angle = math.radians(30)
    rot = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                    [0, 0, 1]])
    ext = SensorExtrinsics(rot, np.array([0.1, -0.2, 0.3]))
    back = ext.inverse().inverse()
    np.testing.assert_allclose(back.rotation, rot, atol=1e-12)
    point = np.array([0.3, 0.4, 2.0])
    cam = ext.rotation @ point + ext.translation_m
    inv = ext.inverse()
    np.testing.assert_allclose(inv.rotation @ cam + inv.translation_m, point, atol=1e-12)


def test_pixel_bounds_by_hand():
    rects = np.array([[16, 96, 72, 152],  # integer 56 px zone
                      [16, 152, 72, 208],  # its right neighbour
                      [0.2, 0.2, 3.7, 3.7],  # centres 1, 2, 3
                      [-0.5, -0.5, 479.5, 639.5],  # the whole image
                      [-50, -50, -10, -10],  # outside
                      [470, 630, 530, 700]], dtype=np.float32)  # clipped at the corner
    bounds = zone_rects_to_pixel_bounds(rects, 480, 640)
    assert bounds.dtype == np.int64
    assert bounds.tolist() == [[16, 96, 72, 152], [16, 152, 72, 208], [1, 1, 4, 4],
                               [0, 0, 480, 640], [0, 0, 0, 0], [470, 630, 480, 640]]
    assert zone_rects_to_pixel_bounds(rects.reshape(2, 3, 4), 480, 640).shape == (2, 3, 4)


def test_mirror_zone_rects_by_hand():
    # Columns [2, 5) = 2, 3, 4 mirror to 7, 6, 5 = [5, 8) in a 10 px image.
    rects = np.array([[0, 0, 1, 2], [0, 2, 1, 5], [1, 0, 2, 2], [1, 2, 2, 5]], np.float32)
    np.testing.assert_array_equal(mirror_zone_rects(rects, width=10, grid=2),
                                  [[0, 5, 1, 8], [0, 8, 1, 10], [1, 5, 2, 8], [1, 8, 2, 10]])
