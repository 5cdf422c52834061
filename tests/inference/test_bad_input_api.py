"""Bad input through the Python API: ValueError naming the argument, never a wrong answer."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from deltar.data.rgbd_files import read_color
from deltar.inference.estimator import DepthEstimator
from deltar.io.torch_file import read_torch_file
from deltar.io.zone_file import load_zone_frame, zone_frame_to_dict
from deltar.sensor.zone_frame import ZoneFrame


@pytest.fixture(scope="module")
def estimator():
    torch.manual_seed(0)
    from deltar.models import create_model

    return DepthEstimator(create_model("deltar-lite", design_size=(64, 96)).eval())


@pytest.fixture
def image(rng):
    return rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)


def _frame(mean=1.5, valid=True, sensor_model="VL53L5CX"):
    mean = np.broadcast_to(np.asarray(mean, dtype=np.float64), (64,)).copy()
    return ZoneFrame(mean, np.full(64, 0.02), np.full(64, valid), sensor_model=sensor_model)


def test_frame_without_valid_zone_gives_a_flagged_image_only_estimate(estimator, image):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said by the result, not by a warning
        result = estimator.predict(image, _frame(0.0, valid=False))
    assert result.image_only and result.zones_used == 0
    assert np.all(result.uncertainty_m >= result.depth_m - 1e-6)
    normal = estimator.predict(image, _frame())
    assert not normal.image_only and normal.zones_used == 64
    assert np.median(normal.uncertainty_m / normal.depth_m) < 1.0


@pytest.mark.parametrize("mean, shown", [(np.r_[1e6, np.full(63, 1.5)], "1e+06"),
                                         (0.0, "zones [0, 1, 2, 3, 4] and 59 more")])
def test_impossible_distances_raise(estimator, image, mean, shown):
    with pytest.raises(ValueError, match="outside the VL53L5CX range 0 < d <= 4 m") as info:
        estimator.predict(image, _frame(mean))
    assert shown in str(info.value) and str(info.value).startswith("frames[0]:")


def test_nan_written_into_a_frame_of_a_batch_names_that_frame(estimator, image):
    good, bad = _frame(), _frame()
    bad.mean_m[3, 3] = np.nan  # after construction, as a reused buffer would
    with pytest.raises(ValueError, match=r"^zone_frame\[1\]: ZoneFrame\.mean_m has NaN or "
                       r"infinite values in valid zones \[\[3, 3\]\]"):
        estimator.predict([image, image], [good, bad])


def test_range_follows_the_sensor_model_and_max_range_m(estimator, image, lite_model):
    far = _frame(np.r_[6.0, np.full(63, 1.5)], sensor_model="OTHER-TOF")
    assert estimator.predict(image, far).zones_used == 64  # unknown model: up to 20 m
    strict = DepthEstimator(lite_model, max_range_m=2.0, fold_batch_norms=False)
    with pytest.raises(ValueError, match="range 0 < d <= 2 m"):
        strict.predict(image, _frame(np.r_[3.0, np.full(63, 1.5)]))
    with pytest.raises(ValueError, match="max_range_m must be a positive number"):
        DepthEstimator(lite_model, max_range_m=float("nan"), fold_batch_norms=False)


@pytest.mark.parametrize("bad, words", [
    (np.zeros((48, 64), np.uint8), "got an array of shape (48, 64)"),
    (torch.zeros(48, 64, 3), "torch Tensor of shape (48, 64, 3); convert it"),
    ({"rgb": 1}, "got a dict"),
    ("frame.png", "str path 'frame.png'; read the file first"),
])
def test_wrong_image_types_say_what_is_expected(estimator, bad, words):
    with pytest.raises(ValueError) as info:
        estimator.predict(bad, _frame())
    message = str(info.value)
    assert message.startswith("image must be an (H, W, 3) uint8 RGB array") and words in message
    assert "images and" not in message  # never "got 48 images"


def test_wrong_zone_frame_and_calibration_types(estimator, image):
    with pytest.raises(ValueError, match=r"zone_frame must be a ZoneFrame .* got a dict"):
        estimator.predict(image, {"mean_m": [1.0]})
    with pytest.raises(ValueError, match=r"zone_frame must be a ZoneFrame .* got a NoneType"):
        estimator.predict(image, None)
    with pytest.raises(ValueError, match=r"calibration must be a RigCalibration .* got a dict"):
        estimator.predict(image, _frame(), calibration={"fx": 1.0})
    with pytest.raises(ValueError, match="list of ZoneFrame"):
        estimator.predict([image, image], _frame())
    # A path says which reader makes the object from it.
    with pytest.raises(ValueError, match=r"got a str path 'z\.json'; read the file first, "
                                         r"e\.g\. with deltar\.io\.zone_file\.load_zone_frame"):
        estimator.predict(image, "z.json")
    with pytest.raises(ValueError, match=r"'c\.json'; read the file first, e\.g\. with "
                                         r"RigCalibration\.load"):
        estimator.predict(image, _frame(), calibration="c.json")


def test_driver_values_must_be_numbers_and_out_of_range_zones_are_invalid():
    with pytest.raises(ValueError, match="distance_mm must hold numbers, got str '1500'"):
        ZoneFrame.from_driver(["1500"] * 64, [20] * 64, [5] * 64)
    with pytest.warns(RuntimeWarning, match="2 zone.* read more than the VL53L5CX's 4 m"):
        frame = ZoneFrame.from_driver([1500] * 62 + [4500, 8000], [20] * 64, [5] * 64)
    assert frame.valid_count == 62


@pytest.mark.parametrize("key, value, words", [
    ("mean_m", ["1.5"] * 64, "mean_m must hold numbers, got str '1.5' and 63 more"),
    ("sigma_m", [True] * 64, "sigma_m must hold numbers, got bool True"),
    ("timestamp_s", "12.5", "timestamp_s must be a number, got '12.5'"),
    ("valid", ["true"] * 64, "valid must hold booleans"),
    ("sensor_model", 5, "sensor_model must be a string"),
    # Seven numbers and a one-number list in the first row: 64 numbers, not a grid.
    ("mean_m", [[1.5] * 7 + [[1.0]]] + [[1.5] * 8] * 7,
     "mean_m must be a flat list of numbers or rows of equal length"),
])
def test_zone_files_refuse_strings_and_booleans(tmp_path, key, value, words):
    data = zone_frame_to_dict(_frame())
    data[key] = value
    path = tmp_path / "z.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError) as info:
        load_zone_frame(path)
    assert str(info.value).startswith(str(path)) and words in str(info.value)


def test_npz_zone_file_with_string_arrays(tmp_path):
    path = tmp_path / "z.npz"
    np.savez(path, mean_m=np.array(["1.0"] * 64), sigma_m=np.zeros(64), valid=np.ones(64, bool),
             schema_version=np.array(1))
    with pytest.raises(ValueError, match="mean_m must hold numbers, got an array of <U3"):
        load_zone_frame(path)


def test_read_color_refuses_depth_maps_and_accepts_grey(tmp_path):
    Image.fromarray(np.full((8, 8), 1000, np.uint16)).save(tmp_path / "d.png")
    with pytest.raises(ValueError, match=r"d\.png is a single-channel 16-bit image"):
        read_color(tmp_path / "d.png")
    Image.fromarray(np.full((8, 8), 7, np.uint8)).save(tmp_path / "g.png")
    assert read_color(tmp_path / "g.png").shape == (8, 8, 3)


def test_torch_file_errors_are_short_and_safe(tmp_path):
    import argparse

    torch.save({"args": argparse.Namespace(x=1)}, tmp_path / "objects.pt")
    with pytest.raises(ValueError) as info:
        read_torch_file(tmp_path / "objects.pt", "checkpoint", weights_only=True)
    message = str(info.value)
    assert "safe loading refuses (it refers to argparse.Namespace)" in message
    assert "weights_only" not in message and "\n" not in message
    (tmp_path / "text.pt").write_text("e" * 50)
    with pytest.raises(ValueError, match=r"text\.pt: cannot read checkpoint: not a PyTorch file"):
        read_torch_file(tmp_path / "text.pt", "checkpoint", weights_only=True)


def test_zone_rectangles_outside_the_image_are_refused_or_counted(estimator, image):
    frame = _frame()
    outside = np.tile(np.array([[100.0, 100.0, 110.0, 110.0]], np.float32), (64, 1))
    with pytest.raises(ValueError, match=r"^frames\[0\]: all 64 valid zones fall outside the "
                       r"48x64 image; check the calibration"):
        estimator.predict(image, frame, zone_rects=outside)
    some = outside.copy()
    some[:16] = [0.0, 0.0, 6.0, 8.0]
    with pytest.warns(UserWarning, match=r"frames\[0\]: 48 of 64 valid zones fall outside "
                      r"the 48x64 image \(16 inside\); they are still read"):
        estimator.predict(image, frame, zone_rects=some)


@pytest.mark.parametrize("changes, message", [
    ({"sigma_m": np.array([1e6] + [0.02] * 63)}, "have a sigma larger than the VL53L5CX "
     "range 4 m"),
    ({"status": np.array([255] + [5] * 63)}, "are valid but their status is 255"),
])
def test_physically_impossible_frames_are_refused(estimator, image, changes, message):
    fields = {"mean_m": np.full(64, 1.5), "sigma_m": np.full(64, 0.02),
              "valid": np.ones(64, bool), **changes}
    with pytest.raises(ValueError, match=message):
        estimator.predict(image, ZoneFrame(**fields))


def test_a_result_keeps_its_own_copy_of_the_readings_and_rectangles(estimator, image):
    frame = _frame()
    rects = estimator.zone_rects_for(frame, image.shape[:2]).astype(np.float32)
    result = estimator.predict(image, frame, zone_rects=rects)
    frame.mean_m[...] *= 0.5  # the caller's buffers, reused for the next reading
    rects += 10.0
    assert np.all(result.zone_frame.mean_m == np.float32(1.5))
    assert not np.shares_memory(result.zone_rects, rects)
    assert np.allclose(result.zone_rects, rects - 10.0)
