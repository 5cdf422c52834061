"""``deltar calibrate --target``, ``deltar calibration-board``, ``deltar check-calibration``."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from deltar.calibration.board import BoardDetector, parse_board_spec
from deltar.calibration.rig import RigCalibration
from deltar.calibration.synthetic_board import board_view_poses, write_board_recording
from deltar.camera import CameraIntrinsics
from deltar.cli.main import app
from deltar.sensor.geometry import SensorExtrinsics

CAMERA = CameraIntrinsics(260.0, 262.0, 161.0, 119.0, 320, 240)
TARGET = "charuco:5x4:0.06:0.045:DICT_4X4_50"
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))


def _run(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def board_recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli_board") / "rec"
    poses = board_view_poses(10, distance_m=(0.5, 0.9), tilt_deg=35, min_tilt_deg=15, seed=6)
    write_board_recording(folder, TRUE, CAMERA, parse_board_spec(TARGET), poses,
                          mean_noise_m=0.01, with_depth=True, seed=6)
    return folder


def test_calibrate_with_a_board_then_check_it(board_recording, tmp_path):
    out = tmp_path / "calib.json"
    result = _run("calibrate", board_recording, "--target", TARGET, "--out", out,
                  "--plot", tmp_path / "plots")
    assert result.exit_code == 0, result.output
    assert "board found in 10 of 10 paired images" in result.output
    assert "printed at" not in result.output  # the spec's size: no scale warning
    # The same board given 6 % larger than printed (a page shrunk to fit): warned.
    with pytest.warns(UserWarning, match="the board looks printed at 0.9"):
        small = _run("calibrate", board_recording, "--target",
                     "charuco:5x4:0.0638:0.0479:DICT_4X4_50", "--out", tmp_path / "small.json")
    assert small.exit_code == 0, small.output
    # ... and the translation error it implies is said beside the expected error.
    off = RigCalibration.load(tmp_path / "small.json").residuals["board_scale_translation_m"]
    assert 0.02 < off < 0.08
    assert f"plus about {1000 * off:.0f} mm of translation from the board's printed size" \
        in small.output
    assert "plus about" not in result.output
    assert RigCalibration.load(out).residuals["board_scale_translation_m"] == 0.0
    assert "frames used: 10" in result.output and "cm before" in result.output
    calib = RigCalibration.load(out)
    # The report prints the expected error the file stores.
    assert (f"rotation {calib.residuals['rotation_sd_deg']:.2f} deg, translation "
            f"{1000 * calib.residuals['translation_sd_m']:.1f} mm") in result.output
    angle = np.degrees(Rotation.from_matrix(calib.extrinsics.rotation @ TRUE.rotation.T)
                       .magnitude())
    assert angle < 1.0 and np.linalg.norm(calib.extrinsics.translation_m -
                                          TRUE.translation_m) < 0.015
    assert calib.residuals["zone_to_cloud_after_m"] < calib.residuals["zone_to_cloud_before_m"]
    assert len(list((tmp_path / "plots").glob("zones_*.png"))) == 3
    # The calibration scores well on the board and on the depth images ...
    for extra in (["--target", TARGET], []):
        check = _run("check-calibration", board_recording, "--calib", out, *extra)
        assert check.exit_code == 0, check.output
        assert "the calibration fits this recording" in check.output
    # ... and a bumped one (3 deg, 3 cm) does not.
    bumped = RigCalibration(calib.intrinsics, SensorExtrinsics(
        Rotation.from_euler("x", 3, degrees=True).as_matrix() @ calib.extrinsics.rotation,
        calib.extrinsics.translation_m + np.array([0, 0, 0.03])))
    bumped.save(tmp_path / "bumped.json")
    check = _run("check-calibration", board_recording, "--calib", tmp_path / "bumped.json",
                 "--target", TARGET, "--plot", tmp_path / "check.png")
    assert check.exit_code == 3 and "does NOT fit" in check.output
    assert (tmp_path / "check.png").stat().st_size > 5000
    median = float(re.search(r"median \|r\| ([\d.]+) cm", check.output).group(1))
    assert median > 2.5
    # The plot never replaces an input, whatever --overwrite says, and is a PNG.
    image = sorted((board_recording / "color").iterdir())[0]
    before = image.read_bytes()
    for plot, message in ((image, "is inside the input"),
                          (tmp_path / "bumped.json", "is not a .png file")):
        refused = _run("check-calibration", board_recording, "--calib",
                       tmp_path / "bumped.json", "--plot", plot, "--overwrite")
        assert refused.exit_code != 0 and message in refused.output
    assert image.read_bytes() == before
    # Zone frames that pair with no image are named as such, not blamed on the board.
    unpaired = _run("calibrate", board_recording, "--target", TARGET, "--out",
                    tmp_path / "late.json", "--time-offset", "1000")
    assert unpaired.exit_code == 1
    assert "has a colour image within 0.02 s" in unpaired.output
    assert "check the time offset" in unpaired.output and "board spec" not in unpaired.output
    few = _run("calibrate", board_recording, "--target", TARGET, "--out",
               tmp_path / "late.json", "--time-offset", "5")
    assert few.exit_code == 1 and "only 5 of the 10 zone frames have a colour image" \
        in few.output


@pytest.mark.parametrize(("args", "message"), [
    (["--target", "charuco:7x5"], "must be charuco:COLSxROWS"),
    (["--calibrate-intrinsics"], "--calibrate-intrinsics needs --target"),
    (["--time-offset", "auto"], "'auto' needs --target"),
    (["--target", TARGET, "--time-offset", "soon"], "must be seconds or 'auto'"),
])
def test_calibrate_board_usage_errors(tmp_path, args, message):
    result = _run("calibrate", tmp_path, "--out", tmp_path / "c.json", *args)
    assert result.exit_code == 2 and message in result.output


def test_calibrate_refuses_a_wrong_board_spec(board_recording, tmp_path):
    result = _run("calibrate", board_recording, "--out", tmp_path / "c.json", "--target",
                  "charuco:5x4:0.06:0.045:DICT_6X6_250")
    assert result.exit_code == 1
    assert "too few views with the board: found in 0 of the 10" in result.output
    assert "markers of DICT_4X4_50 are in the images" in result.output
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize(("paper", "size_px"), [("a4", (1240, 1753)), ("letter", (1275, 1650))])
def test_calibration_board_page_is_true_scale(tmp_path, paper, size_px):
    target = "charuco:7x5:0.03:0.022:DICT_5X5_100"
    out = tmp_path / "board.png"
    result = _run("calibration-board", "--target", target, "--out", out, "--paper", paper,
                  "--dpi", 150)
    assert result.exit_code == 0, result.output
    page = cv2.imread(str(out))
    assert sorted(page.shape[:2]) == sorted(size_px)  # the paper at 150 dpi (+-1 px)
    detection = BoardDetector(parse_board_spec(target)).detect(page[..., ::-1].copy())
    assert detection is not None and len(detection.image_points) == 24
    # Pixels per metre from the corners: 150 dpi is 5905.5 px/m.
    design = np.column_stack([detection.object_points[:, :2], np.ones(24)])
    scale = np.linalg.lstsq(design, detection.image_points, rcond=None)[0][:2]
    assert np.abs(np.linalg.svd(scale, compute_uv=False) - 150 / 0.0254).max() < 0.005 * 5905.5
    pdf = _run("calibration-board", "--target", target, "--out", tmp_path / "b.pdf",
               "--paper", paper)
    assert pdf.exit_code == 0
    box = re.search(rb"MediaBox \[ ?0 0 ([\d.]+) ([\d.]+)", (tmp_path / "b.pdf").read_bytes())
    points = sorted(float(v) for v in box.groups())
    expected = {"a4": [595.28, 841.89], "letter": [612.0, 792.0]}[paper]
    np.testing.assert_allclose(points, expected, atol=0.05)


def test_calibration_board_refuses_a_board_larger_than_the_paper(tmp_path):
    result = _run("calibration-board", "--target", "charuco:7x5:0.05:0.04", "--out",
                  tmp_path / "b.pdf")
    assert result.exit_code == 1 and "does not fit on a4 paper" in result.output
    assert "use squares of at most" in result.output


def test_check_calibration_needs_three_scored_frames(tmp_path):
    folder = tmp_path / "two"
    poses = board_view_poses(2, distance_m=(0.5, 0.9), tilt_deg=35, min_tilt_deg=15, seed=6)
    write_board_recording(folder, TRUE, CAMERA, parse_board_spec(TARGET), poses,
                          mean_noise_m=0.01, with_depth=True, seed=6)
    RigCalibration(CAMERA, TRUE).save(tmp_path / "true.json")
    check = _run("check-calibration", folder, "--calib", tmp_path / "true.json", "--target",
                 TARGET)
    assert check.exit_code == 1
    assert "the board is found in only 2 of 2 paired frames" in check.output
    assert "at least 3" in check.output


def test_check_calibration_names_the_files_it_cannot_match(board_recording, tmp_path):
    four = RigCalibration(CAMERA, TRUE, grid=4).save(tmp_path / "four.json")
    result = _run("check-calibration", board_recording, "--calib", four, "--target", TARGET)
    assert result.exit_code == 1
    assert (f"--calib {four} is for a 4x4 grid, the recording {board_recording} has 8x8"
            in " ".join(result.output.split()))
    late = RigCalibration(CAMERA, TRUE, time_offset_s=30.0).save(tmp_path / "late.json")
    result = _run("check-calibration", board_recording, "--calib", late, "--target", TARGET)
    assert result.exit_code == 1
    assert (f"no zone frame pairs with an image within 0.02 s at --calib {late}'s time offset "
            "of +30 s") in " ".join(result.output.split())


def test_check_calibration_refuses_an_infinite_tolerance(tmp_path):
    # As calibrate does: inf would pair each zone frame with an image any time apart.
    result = _run("check-calibration", tmp_path, "--calib", tmp_path / "c.json",
                  "--tolerance-s", "inf")
    assert result.exit_code == 2
    assert "--tolerance-s" in result.output and "finite" in result.output
