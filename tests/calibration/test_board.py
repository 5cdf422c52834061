"""Board specs, detection and pose on rendered views, closed form, time offset."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.board import (
    BoardDetection,
    BoardDetector,
    calibrate_camera,
    estimate_board_pose,
    parse_board_spec,
)
from deltar.calibration.extrinsic import closed_form_extrinsics
from deltar.calibration.synthetic_board import (
    WALL,
    board_to_world,
    board_view_poses,
    render_board_image,
)
from deltar.calibration.time_offset import estimate_time_offset
from deltar.camera import CameraIntrinsics

SMALL = CameraIntrinsics(260.0, 262.0, 161.0, 119.0, 320, 240)
SPEC = parse_board_spec("charuco:5x4:0.06:0.045:DICT_4X4_50")


def test_spec_parsing_and_sizes():
    spec = parse_board_spec("charuco:7x5:0.04:0.03")
    assert spec.dictionary == "DICT_5X5_100" and spec.marker_count == 17
    assert spec.size_m == pytest.approx((0.28, 0.20))
    assert parse_board_spec(spec.text()) == spec
    board = parse_board_spec("checkerboard:9x6:0.025")
    assert board.squares == (10, 7) and board.size_m == pytest.approx((0.25, 0.175))
    assert SPEC.texture(10).shape == (40, 50)


@pytest.mark.parametrize(("text", "message"), [
    ("charuco:7x5:0.04", "must be charuco:COLSxROWS"),
    ("circles:7x5:0.04", "must be charuco:COLSxROWS"),
    ("charuco:7x5:0.03:0.04", "must be smaller than the square"),
    ("charuco:7x5:40:30", "metres in"),
    ("charuco:7x5:0.04:0.03:DICT_9X9_1", "unknown ArUco dictionary"),
    ("charuco:12x12:0.04:0.03:DICT_4X4_50", "has 72 markers but DICT_4X4_50 holds only 50"),
    ("checkerboard:1x6:0.02", "at least 3x2 inner corners"),
])
def test_bad_specs_name_the_option(text, message):
    with pytest.raises(ValueError, match=message) as info:
        parse_board_spec(text)
    assert "--target" in str(info.value)


@pytest.mark.parametrize("text", ["charuco:5x4:0.06:0.045:DICT_4X4_50",
                                  "checkerboard:6x4:0.05"])
def test_pose_of_a_rendered_board(text):
    """The board's plane from one rendered view, against the true wall plane."""
    spec = parse_board_spec(text)
    pose = board_view_poses(1, distance_m=(0.6, 0.6), tilt_deg=20, min_tilt_deg=10, seed=2)[0]
    image = render_board_image(spec, pose, SMALL)
    detection = BoardDetector(spec).detect(image)
    assert detection is not None and len(detection.image_points) >= 6
    found = estimate_board_pose(detection, SMALL)
    cam_from_world = np.linalg.inv(pose)
    normal = cam_from_world[:3, :3] @ WALL[0, :3]  # wall normal, pointing at the camera
    truth = np.linalg.inv(pose) @ board_to_world(spec)
    assert np.degrees(np.arccos(found.normal_cam @ normal)) < 1.5
    assert found.offset_cam_m == pytest.approx(-normal @ truth[:3, 3], abs=0.005)
    assert found.reprojection_rms_px < 0.5 and found.normal_std_rad > 0


def test_no_board_and_a_wrong_dictionary_are_told_apart():
    pose = board_view_poses(1, distance_m=(0.6, 0.6), seed=1)[0]
    image = render_board_image(SPEC, pose, SMALL)
    wrong = BoardDetector(parse_board_spec("charuco:5x4:0.06:0.045:DICT_6X6_50"))
    assert wrong.detect(image) is None
    assert "markers of DICT_4X4_50 are in the images" in wrong.diagnose([image])
    blank = np.full((240, 320, 3), 150, np.uint8)
    assert BoardDetector(SPEC).detect(blank) is None and wrong.diagnose([blank]) == ""


def test_closed_form_recovers_an_exact_transform():
    rng = np.random.default_rng(0)
    rotation = Rotation.from_euler("zyx", [91.0, 3.0, -2.0], degrees=True).as_matrix()
    translation = np.array([0.03, -0.02, 0.01])
    normals_cam = rng.normal(size=(8, 3)) * [0.4, 0.4, 1.0] + [0, 0, -1]
    normals_cam /= np.linalg.norm(normals_cam, axis=1, keepdims=True)
    offsets_cam = rng.uniform(0.5, 1.5, 8)
    normals_sensor = normals_cam @ rotation  # R^T n
    offsets_sensor = offsets_cam + normals_cam @ translation
    solved = closed_form_extrinsics(normals_sensor, offsets_sensor, normals_cam, offsets_cam)
    np.testing.assert_allclose(solved.rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(solved.translation_m, translation, atol=1e-9)


def test_time_offset_from_distance_series():
    rng = np.random.default_rng(3)

    def distance(t):
        return 0.8 + 0.25 * np.sin(1.3 * t) + 0.1 * np.sin(3.1 * t + 1)

    true_offset = 0.073
    image_stamps = np.arange(0, 8, 1 / 30)            # camera clock
    zone_times = np.arange(0.2, 7.8, 1 / 15)          # sensor clock
    camera = distance(image_stamps - true_offset) + rng.normal(0, 0.002, image_stamps.size)
    zones = distance(zone_times) + 0.02 + rng.normal(0, 0.01, zone_times.size)
    found = estimate_time_offset(image_stamps, camera, zone_times, zones)
    # 1 cm zone noise at ~0.3 m/s: a few ms of scatter (seeds 0-5: 63-80 ms).
    assert found.offset_s == pytest.approx(true_offset, abs=0.015)
    assert found.residual_m < found.residual_at_zero_m
    with pytest.raises(ValueError, match="the board's distance hardly changes"):
        estimate_time_offset(image_stamps, np.full(image_stamps.size, 0.8), zone_times, zones)
    with pytest.raises(ValueError, match="at least 10 images"):
        estimate_time_offset(image_stamps[:5], camera[:5], zone_times, zones)


def test_a_checkerboard_counted_by_squares_is_told_apart():
    """A 6x4-inner-corner board given as 7x5 (its squares): the hint says so."""
    printed = parse_board_spec("checkerboard:6x4:0.05")
    pose = board_view_poses(1, distance_m=(0.6, 0.6), tilt_deg=10, seed=1)[0]
    image = render_board_image(printed, pose, SMALL)
    wrong = BoardDetector(parse_board_spec("checkerboard:7x5:0.05"))
    assert wrong.detect(image) is None
    assert "a checkerboard with 6x4 inner corners is in the images" in wrong.diagnose([image])


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
