"""Calibration with a printed board and no depth camera, on synthetic rigs rendered with
OpenCV's board image: accuracy, the time offset, and every refusal with its message."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.board import parse_board_spec
from deltar.calibration.board_pipeline import calibrate_recording_with_board
from deltar.calibration.extrinsic import nominal_extrinsics
from deltar.calibration.synthetic_board import board_view_poses, write_board_recording
from deltar.camera import CameraIntrinsics
from deltar.io.recording import Recording
from deltar.sensor.geometry import SensorExtrinsics

SMALL = CameraIntrinsics(260.0, 262.0, 161.0, 119.0, 320, 240)
SPEC = parse_board_spec("charuco:5x4:0.06:0.045:DICT_4X4_50")
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))
NOMINAL = nominal_extrinsics(90.0)
#: The guide's views: tilted 25-45 deg.
STEEP = {"tilt_deg": 45.0, "min_tilt_deg": 25.0}


def _errors(found: SensorExtrinsics) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) against TRUE."""
    angle = Rotation.from_matrix(found.rotation @ TRUE.rotation.T).magnitude()
    return float(np.degrees(angle)), float(np.linalg.norm(found.translation_m -
                                                          TRUE.translation_m))


def _poses(count: int = 10, seed: int = 0, **kw):
    kw = {"distance_m": (0.5, 0.9), "tilt_deg": 35.0, "min_tilt_deg": 15.0, **kw}
    return board_view_poses(count, seed=seed, **kw)


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("board") / "rec"
    write_board_recording(folder, TRUE, SMALL, SPEC, _poses(12), mean_noise_m=0.01, seed=0)
    return Recording(folder)


def test_small_rig_calibrates(small_recording):
    # 12 views of a small board tilted 15-35 deg: the result warns that more views are
    # needed for 0.35 deg.
    with pytest.warns(UserWarning, match=r"the 12 board views leave the extrinsic uncertain: "
                                         r"the zones' noise \(1\.\d cm\) allows errors of "
                                         r"about 0\.\d\d deg .* tilted 25-45 deg"):
        result, report = calibrate_recording_with_board(small_recording, SPEC, NOMINAL)
    angle, shift = _errors(result.calibration.extrinsics)
    assert angle < 1.0 and shift < 0.015
    expected = report.uncertainty
    assert expected.zone_noise_m == pytest.approx(0.01, rel=0.2)
    assert angle < 3 * expected.rotation_rms_deg and shift < 3 * expected.translation_rms_m
    assert expected.rotation_rms_deg > 0.35
    assert report.views_with_board == 12 and len(result.observations) == 12
    assert result.distance_after_m < result.distance_before_m
    residuals = result.calibration.residuals
    assert residuals["frames_used"] == 12 and residuals["board_views"] == 12
    assert residuals["rotation_sd_deg"] == expected.rotation_rms_deg
    assert residuals["translation_sd_m"] == expected.translation_rms_m
    # The last step fits the zone readings themselves: what is left is their 1 cm noise.
    assert residuals["zone_reading_rms_m"] == pytest.approx(0.01, rel=0.3)
    assert result.calibration.time_offset_s == 0.0 and result.calibration.distortion == ()


def test_steeper_views_are_expected_to_be_better(tmp_path):
    """The same rig with views tilted 25-45 deg: a smaller expected error, no warning."""
    write_board_recording(tmp_path / "rec", TRUE, SMALL, SPEC,
                          _poses(12, **STEEP), mean_noise_m=0.01,
                          seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result, report = calibrate_recording_with_board(Recording(tmp_path / "rec"), SPEC,
                                                        NOMINAL)
    assert not [w for w in caught if "uncertain" in str(w.message)]
    expected = report.uncertainty
    assert expected.rotation_rms_deg < 0.35 and expected.translation_rms_m < 0.005
    angle, shift = _errors(result.calibration.extrinsics)
    assert angle < 3 * expected.rotation_rms_deg and shift < 3 * expected.translation_rms_m


def test_a_wrong_dictionary_is_refused_with_the_one_seen(small_recording):
    wrong = parse_board_spec("charuco:5x4:0.06:0.045:DICT_5X5_100")
    with pytest.raises(ValueError, match=r"too few views with the board: found in 0 of the 12 "
                                         r"images .* markers of DICT_4X4_50 are in the images"):
        calibrate_recording_with_board(small_recording, wrong, NOMINAL)


def test_a_wrong_square_size_is_refused(small_recording):
    half = parse_board_spec("charuco:5x4:0.03:0.0225:DICT_4X4_50")
    with pytest.raises(ValueError, match=r"does not match what is detected: with 30 mm squares "
                                         r"the board would be 0\.5\d times as far .*\(about "
                                         r"(59|60|61)\.\d mm"):
        calibrate_recording_with_board(small_recording, half, NOMINAL)


def test_a_depth_image_among_the_colour_images_is_named(tmp_path):
    import cv2

    folder = tmp_path / "rec"
    write_board_recording(folder, TRUE, SMALL, SPEC, _poses(12), mean_noise_m=0.01, seed=0)
    recording = Recording(folder)
    depth_like = recording.color_paths[3]
    cv2.imwrite(str(depth_like), np.full((SMALL.height, SMALL.width), 1500, np.uint16))
    with pytest.raises(ValueError, match=rf"{re.escape(str(depth_like))}: a single-channel "
                       r"uint16 image \(a depth map\?\), not an 8-bit colour image"):
        calibrate_recording_with_board(Recording(folder), SPEC, NOMINAL)
    # A 16-bit colour photo is no depth map: it is said to need 8 bits per channel.
    cv2.imwrite(str(depth_like), np.full((SMALL.height, SMALL.width, 3), 1500, np.uint16))
    with pytest.raises(ValueError, match=rf"{re.escape(str(depth_like))}: a 3-channel uint16 "
                       r"image; a colour image must be 8-bit RGB \(convert it, e.g. "
                       r"image >> 8") as caught:
        calibrate_recording_with_board(Recording(folder), SPEC, NOMINAL)
    assert "depth map" not in str(caught.value)


def test_too_few_views_with_the_board(tmp_path):
    poses = _poses(8)
    for pose in poses[3:]:  # the camera looks 1.5 m to the side of the board
        pose[0, 3] += 1.5
    write_board_recording(tmp_path / "rec", TRUE, SMALL, SPEC, poses, seed=1)
    with pytest.raises(ValueError, match=r"found in 3 of the 8 images paired with a zone frame "
                                         r"\(need at least 6\): keep the whole board in view"):
        calibrate_recording_with_board(Recording(tmp_path / "rec"), SPEC, NOMINAL)
    # Found in every view, but too few views: record more.
    write_board_recording(tmp_path / "few", TRUE, SMALL, SPEC, _poses(4), seed=1)
    with pytest.raises(ValueError, match=r"found in 4 of the 4 images paired with a zone frame "
                                         r"\(need at least 6\): record more views"):
        calibrate_recording_with_board(Recording(tmp_path / "few"), SPEC, NOMINAL)


def test_zones_that_miss_the_boards_surface_are_refused(tmp_path):
    # The sensor sees a surface tilted 40 deg, 30 cm in front of the wall the board is on.
    normal = np.array([np.sin(np.radians(40)), 0.0, -np.cos(np.radians(40))])
    other = np.array([[*normal, -0.3 * normal @ [0, 0, -1.0]]])
    write_board_recording(tmp_path / "rec", TRUE, SMALL, SPEC, _poses(8), sensor_planes=other,
                          seed=2)
    with pytest.raises(ValueError, match=r"in \d of the 8 views with the board the zones mostly "
                                         r"miss the surface the board is fixed on"):
        calibrate_recording_with_board(Recording(tmp_path / "rec"), SPEC, NOMINAL)


def test_views_from_one_direction_are_refused_with_degrees(tmp_path):
    poses = _poses(10, tilt_deg=2.0, min_tilt_deg=0.0)
    write_board_recording(tmp_path / "rec", TRUE, SMALL, SPEC, poses, seed=3)
    with pytest.raises(ValueError, match=r"the board was seen from too few directions: its 10 "
                                         r"views give plane orientations .* spread \d\.\d and "
                                         r"\d\.\d deg rms, at least 5\.7 deg rms is needed"):
        calibrate_recording_with_board(Recording(tmp_path / "rec"), SPEC, NOMINAL)


@pytest.mark.slow
def test_time_offset_is_estimated_and_used_for_pairing(tmp_path):
    """The rig moves continuously; the camera's stamps run 60 ms ahead of the sensor's."""
    keys = _poses(9, seed=4, distance_m=(0.45, 1.0))
    key_times = np.arange(9) * 0.75
    write_board_recording(tmp_path / "rec", TRUE, SMALL, SPEC, keys, key_times_s=key_times,
                          image_times_s=np.arange(0.0, 6.0, 1 / 30),
                          zone_times_s=np.arange(0.05, 6.0, 1 / 15), time_offset_s=0.06,
                          mean_noise_m=0.01, seed=4)
    rec = Recording(tmp_path / "rec")
    result, report = calibrate_recording_with_board(rec, SPEC, NOMINAL, time_offset_s="auto",
                                                    tolerance_s=0.034)
    assert report.time_offset.offset_s == pytest.approx(0.06, abs=0.02)
    assert report.time_offset.residual_m < report.time_offset.residual_at_zero_m
    assert result.calibration.time_offset_s == report.time_offset_s
    # Pairing with the offset takes the image about 60 ms after each zone frame's stamp.
    paired = rec.pairs(0.017, time_offset_s=result.calibration.time_offset_s)
    assert np.median([p.color_offset_s for p in paired]) == pytest.approx(0.06, abs=0.02)
    angle, shift = _errors(result.calibration.extrinsics)
    assert angle < 1.0 and shift < 0.015


@pytest.mark.slow
def test_vga_rig_meets_the_accuracy_target(tmp_path):
    """The issue's target: 2 cm zone noise, 15 views tilted 25-45 deg as the guide asks, a
    roll-90 / zero-translation guess (one seed; benchmarks/RESULTS.md has ten)."""
    camera = CameraIntrinsics(500.0, 505.0, 322.0, 238.0, 640, 480)
    spec = parse_board_spec("charuco:7x5:0.04:0.03:DICT_5X5_100")
    write_board_recording(tmp_path / "rec", TRUE, camera, spec, _poses(15, seed=0, **STEEP),
                          seed=0)
    result, _ = calibrate_recording_with_board(Recording(tmp_path / "rec"), spec, NOMINAL)
    angle, shift = _errors(result.calibration.extrinsics)
    assert angle < 0.5 and shift < 0.010


@pytest.mark.slow
@pytest.mark.parametrize("near", [0, 6])
def test_intrinsics_from_8_percent_off(tmp_path, near):
    """20 views; with ``near`` of them 0.3-0.45 m away (the board fills most of the image)
    the principal point is pinned down, without them a warning asks for such views."""
    camera = CameraIntrinsics(500.0, 505.0, 322.0, 238.0, 640, 480)
    rough = CameraIntrinsics(540.0, 465.0, 330.0, 230.0, 640, 480)
    spec = parse_board_spec("charuco:7x5:0.04:0.03:DICT_5X5_100")
    poses = _poses(20 - near, seed=2, **STEEP) + _poses(near, seed=10_002,
                                                        distance_m=(0.3, 0.45), **STEEP)
    write_board_recording(tmp_path / "rec", TRUE, camera, spec, poses,
                          recorded_intrinsics=rough, distortion=(-0.12, 0.05, 0.001, -0.001),
                          seed=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result, report = calibrate_recording_with_board(Recording(tmp_path / "rec"), spec,
                                                        NOMINAL, calibrate_intrinsics=True)
    found = result.calibration.intrinsics
    assert found.fx == pytest.approx(500.0, rel=0.01) and found.fy == pytest.approx(505.0,
                                                                                   rel=0.01)
    assert result.calibration.distortion[0] == pytest.approx(-0.12, abs=0.03)
    assert report.intrinsics_rms_px < 0.5 and report.camera.rms_px == report.intrinsics_rms_px
    angle, shift = _errors(result.calibration.extrinsics)
    assert angle < 0.5 and shift < 0.010
    # The expected error includes the intrinsics' own error.
    expected = report.uncertainty
    assert angle < 3 * expected.rotation_rms_deg and shift < 3 * expected.translation_rms_m
    sd = report.camera.sd
    assert abs(found.cx - 322.0) < 4 * sd[2] and abs(found.cy - 238.0) < 4 * sd[3]
    messages = [str(w.message) for w in caught if "principal point sd" in str(w.message)]
    if near:
        # Pinned down: what is left is mostly the zones' noise.
        assert max(sd[2], sd[3]) < 1.5
        assert all(": record more views, tilted 25-45 deg" in m for m in messages)
    else:
        # The board in the middle of every view: the intrinsics weigh as much as the
        # zones' noise, and the warning asks for close views first.
        assert min(sd[2], sd[3]) > 1.5
        assert len(messages) == 1
        assert re.search(r"the camera intrinsics calibrated from the same views \(principal "
                         r"point sd \d\.\d, \d\.\d px\) 0\.\d\d deg; together 0\.\d\d deg",
                         messages[0])
        assert ": record views close enough that the board fills most of the image (about " \
               "0.3-0.45 m for an A4 board)" in messages[0]
