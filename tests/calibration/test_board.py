"""Board specs, detection and pose on rendered views, closed form, time offset."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.board import BoardDetector, estimate_board_pose, parse_board_spec
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

