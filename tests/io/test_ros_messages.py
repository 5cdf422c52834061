"""ROS 2 messages to numpy: the vl53l5cx_ros2 driver's distance image as a zone frame."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.io.ros_messages import (
    MULTI_TARGET_ZONE_FRAME_MSGTYPE,
    ZONE_FRAME_MSGTYPE,
    stamped_header,
    typestore,
    zone_frame_from_msg,
    zone_frame_from_vl53l5cx_ros2,
)
from deltar.sensor.zone_frame import Orientation

T0 = 1_700_000_000_000_000_000  # a wall-clock stamp, ns


def test_vl53l5cx_ros2_distance_image_adapter():
    store = typestore()
    values = np.arange(64, dtype=np.float32).reshape(8, 8) / 10 + 0.5
    values[0, 1] = np.nan  # a zone the driver marked invalid
    msg = store.types["sensor_msgs/msg/Image"](
        header=stamped_header(T0, "tof"), height=8, width=8, encoding="32FC1",
        is_bigendian=0, step=32, data=values.astype("<f4").view(np.uint8).reshape(-1))
    frame = zone_frame_from_vl53l5cx_ros2(msg, orientation=Orientation(flip_ud=True),
                                          sigma_m=0.03)
    expected = values[::-1]
    assert frame.grid == 8 and frame.timestamp_s == pytest.approx(T0 / 1e9)
    np.testing.assert_array_equal(frame.valid, np.isfinite(expected))
    np.testing.assert_allclose(frame.mean_m[frame.valid], expected[frame.valid])
    assert np.all(frame.sigma_m[frame.valid] == pytest.approx(0.03))
    assert not frame.valid[7, 1]  # row 0 became row 7
    bad = store.types["sensor_msgs/msg/Image"](
        header=stamped_header(T0, "tof"), height=8, width=8, encoding="16UC1",
        is_bigendian=0, step=16, data=np.zeros(128, np.uint8))
    with pytest.raises(ValueError, match="expected a 4x4 or 8x8 32FC1"):
        zone_frame_from_vl53l5cx_ros2(bad)


def test_multi_target_message_lengths_are_checked(rng):
    from deltar.io.ros_messages import stamped_header, typestore

    def message(**changes):
        fields = dict(header=stamped_header(0, "tof"), sensor_model="VL53L5CX", zone_count=16,
                      distance_m=np.full(16, 1.0, np.float32), sigma_m=np.zeros(0, np.float32),
                      status=np.zeros(0, np.uint8), valid=np.zeros(0, bool),
                      hist_edges_m=np.zeros(0, np.float32), hist_counts=np.zeros(0, np.float32),
                      targets_per_zone=2, target_order="strongest",
                      target_distance_m=np.tile(np.float32([1.0, 2.5]), 16),
                      target_sigma_m=np.zeros(0, np.float32), target_status=np.zeros(0, np.uint8),
                      target_valid=np.zeros(0, bool), target_signal=np.zeros(0, np.float32))
        fields.update(changes)
        return typestore().types[MULTI_TARGET_ZONE_FRAME_MSGTYPE](**fields)

    frame = zone_frame_from_msg(message())
    assert frame.target_valid.all() and frame.target_mean_m[0, 0, 1] == np.float32(2.5)
    # Status codes decide validity when no flags are given (5 and 9 valid).
    status = np.tile(np.uint8([5, 4]), 16)
    assert not zone_frame_from_msg(message(target_status=status)).target_valid[..., 1].any()
    with pytest.raises(ValueError, match="zones: target_distance_m has 16 entries; expected "
                                         "zone_count x targets_per_zone = 32"):
        zone_frame_from_msg(message(target_distance_m=np.ones(16, np.float32)))
    with pytest.raises(ValueError, match="target_sigma_m has 3 entries; expected 32 or none"):
        zone_frame_from_msg(message(target_sigma_m=np.ones(3, np.float32)))
    with pytest.raises(ValueError, match=r"targets_per_zone is 0; expected 1\.\.4"):
        zone_frame_from_msg(message(targets_per_zone=0))
    # An empty target_signal: no signals; else one per target, 0 where not valid.
    assert frame.target_signal is None
    signal = np.tile(np.float32([250.0, 30.0]), 16)
    with_signal = zone_frame_from_msg(message(target_signal=signal, target_status=status))
    np.testing.assert_array_equal(with_signal.target_signal[..., 0], 250.0)
    np.testing.assert_array_equal(with_signal.target_signal[..., 1], 0.0)
    with pytest.raises(ValueError, match="target_signal has 16 entries; expected 32 or none"):
        zone_frame_from_msg(message(target_signal=np.ones(16, np.float32)))
    with pytest.raises(ValueError, match=r"zones: ZoneFrame\.target_signal must be finite"):
        zone_frame_from_msg(message(target_signal=np.full(32, -1.0, np.float32)))
    assert ZONE_FRAME_MSGTYPE != MULTI_TARGET_ZONE_FRAME_MSGTYPE


def test_depth_images_in_metres_or_millimetres():
    from deltar.io.ros_messages import metric_image_from_msg

    image = typestore().types["sensor_msgs/msg/Image"]
    millimetres = np.array([[0, 1500, 65535]], dtype=">u2")  # big-endian, as sent
    msg = image(header=stamped_header(T0, "depth"), height=1, width=3, encoding="16UC1",
                is_bigendian=1, step=8, data=np.r_[millimetres.view(np.uint8).reshape(-1),
                                                   np.zeros(2, np.uint8)])
    np.testing.assert_allclose(metric_image_from_msg(msg), [[np.nan, 1.5, 65.535]], atol=1e-6)
    metres = np.array([[np.nan, 2.25]], dtype="<f4")
    msg = image(header=stamped_header(T0, "depth"), height=1, width=2, encoding="32FC1",
                is_bigendian=0, step=8, data=metres.view(np.uint8).reshape(-1))
    np.testing.assert_allclose(metric_image_from_msg(msg), metres)
    msg = image(header=stamped_header(T0, "depth"), height=1, width=2, encoding="mono16",
                is_bigendian=0, step=4, data=np.zeros(4, np.uint8))
    with pytest.raises(ValueError, match="depth_topic: expected encoding 32FC1 or 16UC1"):
        metric_image_from_msg(msg, source="depth_topic")


@pytest.mark.parametrize("stamp_ns", [2**31 * 1_000_000_000, -(2**31 + 1) * 1_000_000_000])
def test_a_stamp_a_ros_time_cannot_hold_is_named(stamp_ns):
    message = rf"a ROS stamp holds at most 2147483647 s either side of 0 .*got {stamp_ns} ns"
    with pytest.raises(ValueError, match=message):
        stamped_header(stamp_ns, "tof")
    assert stamped_header((2**31 - 1) * 1_000_000_000, "tof").stamp.sec == 2**31 - 1
    assert stamped_header(-296_000_000, "tof").stamp.sec == -1  # a clock behind another's
