"""Replay of ROS 2 bags: the frames chosen (time offset, frames without a valid zone)
and errors naming the frame. Bags are written with deltar's own writer."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.calibration.rig import RigCalibration
from deltar.camera import CameraIntrinsics
from deltar.capture.bag_replay import replay_bag
from deltar.inference.estimator import DepthEstimator
from deltar.io.rosbag_reader import BagInput
from deltar.io.rosbag_writer import BagWriter
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import ZonePainterNet

HEIGHT, WIDTH = 48, 64
INTR = CameraIntrinsics(52.0, 52.0, 31.5, 23.5, WIDTH, HEIGHT)
MS = 1_000_000


def _zones(stamp_ns: int, valid: bool = True) -> ZoneFrame:
    mean = np.full((8, 8), 1.5 if valid else 0.0, np.float32)
    return ZoneFrame(mean, np.full((8, 8), 0.02 if valid else 0.0, np.float32),
                     np.full((8, 8), valid), timestamp_s=stamp_ns / 1e9)


def _bag(path, tof_ns: list[int], invalid: tuple[int, ...] = ()) -> BagInput:
    """Images at 0, 100, 200 ms; a ToF frame at each of ``tof_ns`` (those at the
    positions in ``invalid`` without a valid zone)."""
    rng = np.random.default_rng(0)
    writer = BagWriter(path)
    for i in range(3):
        rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        writer.add_rgb_image("/camera/image", i * 100 * MS, "cam", rgb)
        writer.add_camera_info("/camera/camera_info", i * 100 * MS, "cam", INTR)
    for i, stamp in enumerate(tof_ns):
        writer.add_zone_frame("/tof/zones", stamp, "tof", _zones(stamp, i not in invalid))
    writer.close()
    return BagInput(path)


def _estimator():
    return DepthEstimator(ZonePainterNet(), weights="painter")


def test_the_calibrations_time_offset_pairs_unless_one_is_given(tmp_path):
    # The sensor's clock runs 300 ms behind the camera's.
    bag = _bag(tmp_path / "bag", [-300 * MS + 4 * MS, -200 * MS + 4 * MS, -100 * MS + 4 * MS])
    calib = RigCalibration(INTR, SensorExtrinsics(), grid=8, time_offset_s=0.3)
    items = list(replay_bag(bag, _estimator(), calibration=calib))
    assert [i.pair.image_index for i in items] == [0, 1, 2]
    with pytest.raises(ValueError, match="no ToF message on /tof/zones has a camera image"):
        list(replay_bag(bag, _estimator(), calibration=calib, time_offset_s=0.0))


def test_a_frame_without_a_valid_zone_is_skipped_or_written_with_a_warning(tmp_path):
    bag = _bag(tmp_path / "bag", [4 * MS, 104 * MS, 204 * MS], invalid=(1,))
    with pytest.warns(UserWarning, match=rf"/tof/zones frame stamped {104 * MS} ns has no "
                      "valid zone; skipped"):
        items = list(replay_bag(bag, _estimator(), skip_no_zones=True, limit=2))
    # The limit counts predicted frames: the skipped one does not take a place.
    assert [i.pair.image_index for i in items] == [0, 2]
    with pytest.warns(UserWarning, match="has no valid zone; image-only estimate"):
        items = list(replay_bag(bag, _estimator()))
    assert [i.prediction.image_only for i in items] == [False, True, False]


def test_a_refused_frame_names_the_topic_and_stamp(tmp_path):
    bag = _bag(tmp_path / "bag", [4 * MS, 104 * MS])

    class Refusing:
        def predict(self, *args, **kwargs):
            raise ValueError("refused")

    with pytest.raises(ValueError, match=rf"bag: /tof/zones frame stamped {4 * MS} ns: "
                       "refused"):
        list(replay_bag(bag, Refusing()))
