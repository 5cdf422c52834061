"""deltar.camera: the one image check and the one back-projection."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.camera import (
    CameraIntrinsics,
    backproject,
    backproject_pixels,
    check_image,
    pixel_rays,
)

K = CameraIntrinsics(2.0, 4.0, 0.5, 0.5, 3, 2)


def test_backproject_by_hand_skips_invalid_pixels():
    depth = np.array([[1.0, 0.0, np.inf], [2.0, -1.0, 4.0]])
    points, rows, cols = backproject_pixels(depth, K)
    # Pixel (u, v) = (0, 0) at 1 m: x = (0 - 0.5) / 2, y = (0 - 0.5) / 4.
    np.testing.assert_allclose(points, [[-0.25, -0.125, 1.0], [-0.5, 0.25, 2.0],
                                        [3.0, 0.5, 4.0]])
    assert rows.tolist() == [0, 1, 1] and cols.tolist() == [0, 0, 2]


def test_points_lie_on_the_pixel_rays():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (2, 3))
    rays = pixel_rays(K)
    np.testing.assert_allclose(backproject(depth, K), (rays * depth[..., None]).reshape(-1, 3))
    assert pixel_rays(K, 4, 5).shape == (4, 5, 3)


def test_mask_and_stride_select_pixels():
    depth = np.ones((2, 3))
    mask = np.array([[True, False, True], [False, False, True]])
    assert len(backproject(depth, K, mask)) == 3
    _, rows, cols = backproject_pixels(depth, K, stride=2)
    assert list(zip(rows.tolist(), cols.tolist(), strict=True)) == [(0, 0), (0, 2)]


@pytest.mark.parametrize(("depth", "kwargs", "message"), [
    (np.ones((3, 3)), {}, "depth_m is 3x3 pixels but the intrinsics are for 2x3"),
    (np.ones(6), {}, r"depth_m must be an \(H, W\) array"),
    (np.full((2, 3), np.nan), {}, "NaN"),
    (np.ones((2, 3)), {"mask": np.ones((2, 2), bool)}, "mask must have shape"),
    (np.ones((2, 3)), {"stride": 0}, "stride must be a positive integer"),
])
def test_bad_input_names_the_argument(depth, kwargs, message):
    with pytest.raises(ValueError, match=message):
        backproject_pixels(depth, K, **kwargs)


def test_the_point_cloud_writer_back_projects_as_the_camera_does():
    from deltar.calibration.extrinsic import depth_to_points
    from deltar.inference.outputs import depth_to_points as cloud_points

    depth = np.array([[1.0, 0.0, 2.0], [3.0, 4.0, 5.0]])
    np.testing.assert_array_equal(depth_to_points(depth, K), backproject(depth, K))
    points, colors = cloud_points(depth, K)
    np.testing.assert_allclose(points, backproject(depth, K), rtol=1e-6)
    assert points.dtype == np.float32 and colors.shape == (5, 3)


@pytest.mark.parametrize(("image", "size", "message"), [
    (np.zeros((4, 5, 3), np.float32), None, r"frame\.png must be an \(H, W, 3\) uint8 RGB"),
    (np.zeros((4, 5), np.uint8), None, r"got shape \(4, 5\)"),
    (np.zeros((4, 5, 4), np.uint8), None, "uint8 RGB image"),
    (np.zeros((1, 5, 3), np.uint8), None, "frame.png is too small: 1x5 pixels"),
    (np.zeros((4, 5, 3), np.uint8), (4, 6), "frame.png is 4x5 pixels, expected 4x6"),
])
def test_check_image_names_the_image_and_what_is_wrong(image, size, message):
    with pytest.raises(ValueError, match=message):
        check_image(image, "frame.png", size)


def test_check_image_returns_a_contiguous_image():
    image = np.zeros((4, 10, 3), np.uint8)[:, ::2]
    checked = check_image(image, size=(4, 5))
    assert checked.flags.c_contiguous and checked.shape == (4, 5, 3)
    assert check_image(checked) is checked


def test_undistorted_coverage_is_what_undistortion_leaves_with_a_source():
    import cv2

    from deltar.camera import undistorted_coverage

    camera = CameraIntrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    assert undistorted_coverage(camera, ()) == 1.0
    assert undistorted_coverage(camera, (-0.3, 0.1, 0.0, 0.0, 0.0)) == 1.0  # barrel
    for distortion in ((0.2, 0.0, 0.0, 0.0), (0.0, 0.0, 0.05, -0.03), (1e6,) * 5):
        matrix = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
        map_x, map_y = cv2.initUndistortRectifyMap(matrix, np.array(distortion), None, matrix,
                                                   (640, 480), cv2.CV_32FC1)
        inside = (map_x >= -0.5) & (map_x <= 639.5) & (map_y >= -0.5) & (map_y <= 479.5)
        assert undistorted_coverage(camera, distortion) == pytest.approx(inside.mean(),
                                                                          abs=0.02)
