"""The rig calibration file and zone placement in the image."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace

import numpy as np
import pytest

from deltar.calibration.extrinsic import nominal_extrinsics
from deltar.calibration.rig import RigCalibration
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame

CAMERA = CameraIntrinsics(500.0, 480.0, 319.5, 239.5, 640, 480)


def _calib(**kw) -> RigCalibration:
    return RigCalibration(CAMERA, nominal_extrinsics(90.0, (0.02, -0.01, 0.0)),
                          residuals={"zone_to_cloud_after_m": 0.015}, **kw)


def test_round_trip(tmp_path):
    calib = _calib(fov_deg=(44.0, 46.0))
    path = calib.save(tmp_path / "calib.json")
    back = RigCalibration.load(path)
    assert back.intrinsics == CAMERA
    np.testing.assert_allclose(back.extrinsics.rotation, calib.extrinsics.rotation)
    np.testing.assert_allclose(back.extrinsics.translation_m, [0.02, -0.01, 0.0])
    assert back.fov_deg == (44.0, 46.0) and back.grid == 8
    assert back.residuals == {"zone_to_cloud_after_m": 0.015}
    assert back.date == calib.date and back.date.startswith("20")
    with pytest.raises(FileExistsError):
        calib.save(path)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["extrinsics"].update(rotation=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]),
         "rotation"),
        (lambda d: d.update(grid=5), "grid"),
        (lambda d: d.update(schema_version=7), "schema_version"),
        (lambda d: d.pop("intrinsics"), "intrinsics"),
        (lambda d: d.update(schema="something else"), "not a deltar rig calibration"),
    ],
)
def test_invalid_files_name_the_file(tmp_path, edit, message):
    data = json.loads(_calib().save(tmp_path / "ok.json").read_text())
    edit(data)
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=message) as info:
        RigCalibration.load(tmp_path / "bad.json")
    assert "bad.json" in str(info.value)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        RigCalibration.load(tmp_path / "none.json")
    (tmp_path / "cut.json").write_text('{"schema": ')
    with pytest.raises(ValueError, match="corrupt JSON"):
        RigCalibration.load(tmp_path / "cut.json")


def test_zone_rects_without_offset_are_the_projected_angles():
    calib = RigCalibration(CAMERA, SensorExtrinsics(), grid=4)
    rects = calib.zone_rects_for(1.5, (480, 640))
    # Zone 0 spans -22.5..-11.25 deg in both axes; zone 15 ends at +22.5 deg.
    t0, t1 = np.tan(np.radians(-22.5)), np.tan(np.radians(-11.25))
    np.testing.assert_allclose(rects[0], [480 * t0 + 239.5, 500 * t0 + 319.5,
                                          480 * t1 + 239.5, 500 * t1 + 319.5], atol=1e-3)
    np.testing.assert_allclose(rects[15, 2:], [480 * -t0 + 239.5, 500 * -t0 + 319.5],
                               atol=1e-3)


def test_zone_rects_from_a_frame_use_each_zone_depth():
    calib = _calib()
    mean = np.linspace(0.5, 3.0, 64)
    valid = np.ones(64, bool)
    valid[10] = False
    frame = ZoneFrame(np.where(valid, mean, 0), np.full(64, 0.01) * valid, valid)
    rects = calib.zone_rects_for(frame, (480, 640))
    depths = np.where(valid, mean, np.median(mean[valid]))
    np.testing.assert_allclose(rects, calib.zone_rects_for(depths, (480, 640)), atol=1e-3)
    # With a 2 cm offset, parallax moves near zones more than far ones.
    near = calib.zone_rects_for(0.5, (480, 640))
    far = calib.zone_rects_for(3.0, (480, 640))
    assert np.all(np.abs(near[:, 1] - far[:, 1]) > 1.0)


def test_zone_rects_reject_another_resolution_or_grid():
    calib = _calib()
    with pytest.raises(ValueError, match="is for the calibrated resolution 480x640"):
        calib.zone_rects_for(2.0, (240, 320))
    frame16 = ZoneFrame(np.ones(16), np.zeros(16), np.ones(16, bool))
    with pytest.raises(ValueError, match="grid"):
        calib.zone_rects_for(frame16, (480, 640))


def test_image_size_check_names_the_images_and_the_calibration():
    calib = _calib()
    calib.check_image_size((480, 640))
    with pytest.raises(ValueError, match=r"^the recording r is 240x320 pixels but --calib c\.json "
                                         r"is for the calibrated resolution 480x640"):
        calib.check_image_size((240, 320), "the recording r", "--calib c.json")


def test_distortion_and_time_offset_round_trip_and_undistort(tmp_path):
    import cv2

    calib = _calib(distortion=(-0.2, 0.05, 0.0, 0.0, 0.0), time_offset_s=0.04)
    back = RigCalibration.load(calib.save(tmp_path / "d.json"))
    assert back.distortion == (-0.2, 0.05, 0.0, 0.0, 0.0) and back.time_offset_s == 0.04
    # Files without the fields read as a pinhole camera on the sensor's clock.
    data = json.loads((tmp_path / "d.json").read_text())
    del data["distortion"], data["time_offset_s"]
    (tmp_path / "old.json").write_text(json.dumps(data))
    old = RigCalibration.load(tmp_path / "old.json")
    assert old.distortion == () and old.time_offset_s == 0.0 and not old.has_distortion
    # A point seen through the lens lands at its pinhole position after undistorting.
    image = np.zeros((480, 640), np.uint8)
    point = np.array([[[0.35, 0.25, 1.0]]])
    seen = cv2.projectPoints(point, np.zeros(3), np.zeros(3), CAMERA.matrix,
                             np.array(calib.distortion))[0].ravel()
    image[round(seen[1]) - 1:round(seen[1]) + 2, round(seen[0]) - 1:round(seen[0]) + 2] = 255
    fixed = calib.undistort_image(image)
    rows, cols = np.nonzero(fixed > 100)
    pinhole = (CAMERA.fx * 0.35 + CAMERA.cx, CAMERA.fy * 0.25 + CAMERA.cy)
    assert abs(cols.mean() - pinhole[0]) < 1.0 and abs(rows.mean() - pinhole[1]) < 1.0
    assert old.undistort_image(image) is image
    with pytest.raises(ValueError, match="distortion must be 0, 4, 5"):
        _calib(distortion=(0.1, 0.2, 0.3))
    # Coefficients no lens has: the undistorted image would be black.
    with pytest.raises(ValueError, match=r"leaves 100 % of the undistorted image without a "
                       r"source pixel"):
        _calib(distortion=(1e6,) * 5)
    _calib(distortion=(0.2, 0.0, 0.0, 0.0, 0.0))  # a strong real pincushion keeps 84 %
    # A depth map keeps only depths it holds: nearest pixels, no blend across an edge.
    depth = np.where(np.arange(640)[None, :] < 320, 1.0, 3.0).astype(np.float32).repeat(480, 0)
    moved = calib.undistort_image(depth, nearest=True)
    assert set(np.unique(moved)) <= {0.0, 1.0, 3.0} and (moved == 1.0).any()
    assert not set(np.unique(calib.undistort_image(depth))) <= {0.0, 1.0, 3.0}
    # What remap cannot take is named (was OpenCV's assertion).
    for bad in (depth.astype(np.int64), depth > 1, depth[None], None):
        with pytest.raises(ValueError, match=r"^image must be \(H, W\) or \(H, W, C\) of"):
            calib.undistort_image(bad)


def test_undistorting_keeps_its_maps_and_matches_opencv():
    """The maps made on first use give OpenCV's ``undistort`` for every later image."""
    import cv2

    calib = _calib(distortion=(-0.25, 0.08, 0.001, -0.002, 0.01))
    rng = np.random.default_rng(0)
    for image in (rng.integers(0, 256, (480, 640, 3), dtype=np.uint8),
                  rng.uniform(0, 5, (480, 640)).astype(np.float32)):
        expected = cv2.undistort(image, CAMERA.matrix, np.array(calib.distortion), None,
                                 CAMERA.matrix)
        for _ in range(2):  # first use makes the maps, the second reads them
            np.testing.assert_allclose(calib.undistort_image(image), expected, atol=1e-5)
    # Pickles and copies carry the fields, not the megabytes of maps (remade on use).
    import copy
    import pickle

    assert len(pickle.dumps(calib)) < 4096
    np.testing.assert_array_equal(copy.deepcopy(calib).undistort_image(image),
                                  calib.undistort_image(image))
    pinhole = calib.undistorted()
    assert pinhole == replace(calib, distortion=()) and not pinhole.has_distortion
    assert pinhole.undistorted() is pinhole and calib.undistorted() is pinhole  # made once


@pytest.mark.parametrize("intrinsics, extrinsics, message", [
    (CameraIntrinsics(500.0, 480.0, 900.0, 239.5, 640, 480), None,
     "the principal point (cx, cy) = (900, 239.5) px lies outside the 480x640 image"),
    (CAMERA, SensorExtrinsics(np.eye(3), np.array([20.0, -10.0, 0.0])),
     "the sensor is 22.3607 m from the camera (translation_m [20.0, -10.0, 0.0]); a rig's "
     "sensor sits within 1 m of it (millimetres written as metres?)"),
    (CAMERA, SensorExtrinsics(nominal_extrinsics(0.0, (0, 0, 0)).rotation @ np.array(
        [[1.0, 0, 0], [0, np.cos(1.2), -np.sin(1.2)], [0, np.sin(1.2), np.cos(1.2)]]),
        np.zeros(3)),
     "all 64 zones fall outside the 480x640 image at 2 m; check the extrinsics"),
], ids=["principal-point", "translation-in-mm", "zones-outside"])
def test_impossible_rigs_are_refused(intrinsics, extrinsics, message):
    with pytest.raises(ValueError) as caught:
        RigCalibration(intrinsics, extrinsics or SensorExtrinsics())
    assert message in str(caught.value)


def test_a_rig_with_zones_partly_outside_loads_with_a_warning(tmp_path):
    tilted = SensorExtrinsics(np.array([[1.0, 0, 0], [0, np.cos(0.45), -np.sin(0.45)],
                                        [0, np.sin(0.45), np.cos(0.45)]]), np.zeros(3))
    path = RigCalibration(CAMERA, tilted).save(tmp_path / "c.json")
    inside = int(RigCalibration(CAMERA, tilted).zones_inside().sum())
    assert 0 < inside < 64
    with pytest.warns(UserWarning, match=rf"c\.json: only {inside} of 64 zones fall inside "
                      r"the 480x640 image \(at 2 m\); the others carry no information"):
        RigCalibration.load(path)


@pytest.mark.parametrize("kwargs, message", [
    ({"fov_deg": ("45", "45")}, "RigCalibration.fov_deg must be a number, got '45'"),
    ({"time_offset_s": "0.1"}, "RigCalibration.time_offset_s must be a number, got '0.1'"),
    ({"distortion": (True, 0, 0, 0)}, "RigCalibration.distortion must be a number, got True"),
    ({"grid": True}, "RigCalibration.grid must be 4 or 8 and sensor_model a string"),
], ids=["fov-strings", "offset-string", "distortion-bool", "grid-bool"])
def test_api_values_are_refused_not_coerced(kwargs, message):
    with pytest.raises(ValueError) as caught:
        RigCalibration(CAMERA, SensorExtrinsics(), **kwargs)
    assert message in str(caught.value)
    with pytest.raises(ValueError, match=r"SensorExtrinsics\.translation_m must hold numbers"):
        SensorExtrinsics(np.eye(3), ["0.1", "0", "0"])


def test_a_file_whose_lens_distortion_folds_the_image_loads_with_a_warning(tmp_path):
    """A calibration made elsewhere (e.g. k1 alone fitted to central views) whose radial
    map turns back before the image corners: undistorting folds the outer pixels."""
    path = _calib(distortion=(-0.6, 0.0, 0.0, 0.0, 0.0)).save(tmp_path / "c.json")
    with pytest.warns(UserWarning, match=r"c\.json: its lens distortion \(k1 -0\.6, k2 0\) "
                                         r"turns back at \d+ % of the way"):
        RigCalibration.load(path)
    good = _calib(distortion=(-0.2, 0.05, 0.0, 0.0, 0.0)).save(tmp_path / "good.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        RigCalibration.load(good)


def test_pairing_time_offset_is_the_given_one_else_the_calibrations_else_zero():
    from deltar.calibration.rig import pairing_time_offset

    calib = replace(_calib(), time_offset_s=0.03)
    assert pairing_time_offset(calib, -0.01) == -0.01
    assert pairing_time_offset(calib) == 0.03
    assert pairing_time_offset(None) == 0.0
    assert pairing_time_offset(None, 0.02) == 0.02
