"""Camera intrinsics from board views: the solve started again, its covariance."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.calibration.board import BoardDetection, parse_board_spec
from deltar.calibration.board_camera import calibrate_camera
from deltar.calibration.synthetic_board import board_to_world, board_view_poses
from deltar.camera import CameraIntrinsics

VGA = CameraIntrinsics(500.0, 505.0, 322.0, 238.0, 640, 480)
VGA_GUESS = CameraIntrinsics(540.0, 464.6, 330.0, 230.0, 640, 480)  # fx +8 %, fy -8 %
LENS = (-0.12, 0.05, 0.001, -0.001)
A4 = parse_board_spec("charuco:7x5:0.04:0.03:DICT_5X5_100")


def _projected_views(poses, partial=(), noise_px=0.1, seed=0):
    """The A4 board's inner corners seen by the VGA camera with its lens, plus Gaussian
    noise (pixels); views whose index is in ``partial`` lose the upper-left 6 corners."""
    import cv2

    corners = np.mgrid[1:5, 1:7].reshape(2, -1)[::-1].T * A4.square_m
    full = np.column_stack([corners, np.zeros(len(corners))])
    rng = np.random.default_rng(seed)
    views = []
    for index, pose in enumerate(poses):
        board = np.linalg.inv(pose) @ board_to_world(A4)
        obj = full[(full[:, 1] > 0.1) | (full[:, 0] > 0.14)] if index in partial else full
        image, _ = cv2.projectPoints(obj, cv2.Rodrigues(board[:3, :3])[0], board[:3, 3],
                                     VGA.matrix, np.array(LENS))
        image = image.reshape(-1, 2) + rng.normal(0.0, noise_px, (len(obj), 2))
        views.append(BoardDetection(image.astype(np.float32), obj.astype(np.float32)))
    return views


def _far_and_near(far: int, near: int):
    """Views 0.5-0.9 m away tilted 25-45 deg, and ``near`` 0.3-0.45 m away."""
    tilt = {"tilt_deg": 45.0, "min_tilt_deg": 25.0}
    return (board_view_poses(far, distance_m=(0.5, 0.9), seed=2, **tilt)
            + board_view_poses(near, distance_m=(0.3, 0.45), seed=10_002, **tilt))


def test_camera_calibration_does_not_stop_early():
    """From a guess 8 % off, one OpenCV solve stops at 0.35 px on these views (a view
    seen partly is first posed wrongly); started again it reaches the solve started at
    the true intrinsics."""
    import cv2

    views = _projected_views(_far_and_near(14, 4), partial=(6,))
    found = calibrate_camera(views, VGA_GUESS)
    from_truth = cv2.calibrateCamera([v.object_points for v in views],
                                     [v.image_points for v in views], (640, 480),
                                     VGA.matrix.copy(), np.zeros(5),
                                     flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3)[0]
    assert found.rms_px == pytest.approx(from_truth, rel=0.01)
    assert found.rms_px == pytest.approx(0.1 * np.sqrt(2), rel=0.15)
    k = found.intrinsics
    assert k.fx == pytest.approx(500.0, rel=0.005) and k.fy == pytest.approx(505.0, rel=0.005)
    assert abs(k.cx - 322.0) < 4 * found.sd[2] and abs(k.cy - 238.0) < 4 * found.sd[3]
    assert found.views == 18


def test_camera_covariance_is_opencvs_and_near_views_shrink_it():
    import cv2

    far = _projected_views(_far_and_near(20, 0))
    found = calibrate_camera(far, VGA_GUESS)
    sd = cv2.calibrateCameraExtended([v.object_points for v in far],
                                     [v.image_points for v in far], (640, 480),
                                     VGA_GUESS.matrix.copy(), np.zeros(5),
                                     flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3)[5]
    np.testing.assert_allclose(found.sd, np.ravel(sd)[:8], rtol=1e-3)
    assert found.covariance.shape == (8, 8)
    np.testing.assert_allclose(found.covariance, found.covariance.T, atol=1e-12)
    # A principal point off by sd px turns every board plane by about sd / f radians.
    assert found.principal_point_sd_deg == pytest.approx(
        np.degrees(np.hypot(found.sd[2] / 500.0, found.sd[3] / 505.0)), rel=0.01)
    # The small board in the middle of every view leaves the principal point loose;
    # six of twenty views close enough for it to fill most of the image pin it down.
    near = calibrate_camera(_projected_views(_far_and_near(14, 6)), VGA_GUESS)
    assert near.sd[2] < 0.6 * found.sd[2] and near.sd[3] < 0.6 * found.sd[3]


def test_a_distortion_that_turns_back_inside_the_image_is_refused():
    """k1 alone at -0.4 makes the radial map reach a lens radius of 0.61 at most, inside a
    640-pixel-wide image at fx = 500 (corner radius 0.80): the image's outer pixels have no
    pinhole position. A real lens's (and one bending as far out with k2 > 0) passes."""
    from deltar.calibration.board_camera import check_distortion_covers_image

    check_distortion_covers_image(VGA, LENS)
    check_distortion_covers_image(VGA, (-0.4, 0.2, 0.0, 0.0, 0.0))
    check_distortion_covers_image(VGA, ())
    with pytest.raises(ValueError, match=r"turns back at 7\d % of the way .* Add views with "
                                         r"the board near the image's edges"):
        check_distortion_covers_image(VGA, (-0.4, 0.0, 0.0, 0.0, 0.0))
    # A strong k1 with k3 bending it back is refused too (k3's own term counts), and a
    # pincushion-like fit whose undistorted image folds before the corners (k1 > 0,
    # k2 < 0: the map turns back at a pinhole radius of 0.78, the corner's is 0.80).
    with pytest.raises(ValueError, match="turns back"):
        check_distortion_covers_image(VGA, (0.0, 0.0, 0.0, 0.0, -1.0))
    with pytest.raises(ValueError, match=r"turns back at 98 % .* folds or leaves out"):
        check_distortion_covers_image(VGA, (1.3, -1.8, 0.0, 0.0, 0.0))
