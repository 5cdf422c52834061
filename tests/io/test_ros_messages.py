"""ROS 2 messages to numpy: the vl53l5cx_ros2 driver's distance image as a zone frame."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.io.ros_messages import stamped_header, typestore, zone_frame_from_vl53l5cx_ros2
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
