"""``check_calibration``'s verdict on the true calibration and on turned ones."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.board import parse_board_spec
from deltar.calibration.check import check_calibration
from deltar.calibration.rig import RigCalibration
from deltar.calibration.synthetic_board import board_view_poses, write_board_recording
from deltar.camera import CameraIntrinsics
from deltar.io.recording import Recording
from deltar.sensor.geometry import SensorExtrinsics

CAMERA = CameraIntrinsics(260.0, 262.0, 161.0, 119.0, 320, 240)
SPEC = parse_board_spec("charuco:5x4:0.06:0.045:DICT_4X4_50")
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [178.0, 3.0, -2.0], degrees=True)
                        .as_matrix(), np.array([0.03, 0.0, 0.0]))


@pytest.fixture(scope="module", params=[(8, 0.01), (8, 0.02), (4, 0.02)],
                ids=["8x8-1cm", "8x8-2cm", "4x4-2cm"])
def rig(request, tmp_path_factory):
    grid, noise = request.param
    folder = tmp_path_factory.mktemp("check") / "rec"
    poses = board_view_poses(15, distance_m=(0.5, 0.9), tilt_deg=45, min_tilt_deg=25, seed=1)
    write_board_recording(folder, TRUE, CAMERA, SPEC, poses, mean_noise_m=noise, grid=grid,
                          with_depth=True, seed=1)
    return Recording(folder), RigCalibration(CAMERA, TRUE, grid=grid)


def _turned(calib: RigCalibration, axis: str, degrees: float) -> RigCalibration:
    """The calibration with the sensor turned about its own ``axis``."""
    turn = Rotation.from_euler(axis, degrees, degrees=True).as_matrix()
    ext = calib.extrinsics
    return replace(calib, extrinsics=SensorExtrinsics(ext.rotation @ turn, ext.translation_m))


@pytest.mark.parametrize("spec", [SPEC, None], ids=["board", "depth"])
def test_the_true_calibration_fits(rig, spec):
    recording, calib = rig
    assert check_calibration(recording, calib, spec=spec).fits


@pytest.mark.parametrize(("axis", "degrees"), [("x", 5.0), ("y", -5.0), ("z", 20.0)])
def test_a_sensor_turned_by_degrees_does_not_fit(rig, axis, degrees):
    """A zone is 5.6 deg wide: 5 deg of pitch or yaw puts every zone a zone off. The
    residuals' median and bias can stay under their thresholds (they did for these on
    the 1 cm rig); the tilt across the zone map does not."""
    recording, calib = rig
    for spec in (SPEC, None):
        check = check_calibration(recording, _turned(calib, axis, degrees), spec=spec)
        assert not check.fits, (check.median_abs_m, check.bias_m)

