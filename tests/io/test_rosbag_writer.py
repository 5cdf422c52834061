"""Writing ROS 2 bags: coloured point clouds, zone frames with their no-target flags."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.capture.bag_replay import replay_bag_to_bag
from deltar.inference.estimator import DepthEstimator
from deltar.io.ros_messages import metric_image_from_msg, zone_frame_from_msg
from deltar.io.rosbag_reader import BagInput, read_messages
from deltar.io.rosbag_writer import BagWriter
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import ZonePainterNet
from tests.io.test_rosbag_reader import INTR, read_topic, write_input_bag
from tests.io.test_zone_file import _assert_same_targets, _target_frame


def test_point_cloud_holds_back_projected_coloured_points(tmp_path):
    source = tmp_path / "in_bag"
    truth = write_input_bag(source, frames=1)
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    out, _ = replay_bag_to_bag(BagInput(source), estimator, tmp_path / "out", points=True,
                               point_stride=1, storage="mcap")
    (_, cloud), = read_topic(out, "/deltar/points")
    (_, depth_msg), = read_topic(out, "/deltar/depth")
    depth = metric_image_from_msg(depth_msg)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb"]
    assert cloud.point_step == 16 and cloud.height == 1
    data = np.asarray(cloud.data, dtype=np.uint8).view(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    assert cloud.width == np.isfinite(depth).sum() == data.size
    # Pick the point of pixel (v, u) by back-projecting it and compare colours.
    v, u = np.argwhere(np.isfinite(depth))[len(data) // 2]
    z = depth[v, u]
    expected = np.array([(u - INTR.cx) / INTR.fx * z, (v - INTR.cy) / INTR.fy * z, z])
    xyz = np.stack([data["x"], data["y"], data["z"]], axis=1)
    index = np.argmin(np.linalg.norm(xyz - expected, axis=1))
    np.testing.assert_allclose(xyz[index], expected, atol=1e-5)
    r, g, b = truth["rgb"][0][v, u].astype(np.uint32)
    assert data["rgb"][index] == (r << 16) | (g << 8) | b


def test_no_target_flags_survive_a_bag(tmp_path):
    valid = np.ones((8, 8), bool)
    valid[0, :3] = False
    no_target = np.zeros((8, 8), bool)
    no_target[0, :2] = True  # zone (0, 2) is invalid for another reason
    frame = ZoneFrame(mean_m=np.where(valid, 1.5, 0.0), sigma_m=np.full((8, 8), 0.02),
                      valid=valid, no_target=no_target)
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_zone_frame("/tof/zones", 1_000, "tof", frame)
    ((_, msg),) = read_messages(tmp_path / "bag", "/tof/zones")
    back = zone_frame_from_msg(msg)
    np.testing.assert_array_equal(back.valid, valid)
    np.testing.assert_array_equal(back.no_target, no_target)
    assert back.status.reshape(-1)[:3].tolist() == [255, 255, 0]


def test_no_target_flags_beside_other_status_codes_are_written_as_255(tmp_path):
    valid = np.ones(16, bool)
    valid[:2] = False
    status = np.where(valid, 5, 4).astype(np.uint8)  # zone 0: flagged by a target count
    frame = ZoneFrame(mean_m=np.where(valid, 1.0, 0.0), sigma_m=np.zeros(16), valid=valid,
                      status=status, no_target=np.arange(16) == 0)
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_zone_frame("/tof/zones", 1_000, "tof", frame)
    ((_, msg),) = read_messages(tmp_path / "bag", "/tof/zones")
    back = zone_frame_from_msg(msg)
    assert back.status.reshape(-1)[:3].tolist() == [255, 4, 5]
    assert np.flatnonzero(back.flat_no_target()).tolist() == [0]


def test_bag_round_trip_writes_the_multi_target_message(tmp_path, rng):
    frame = _target_frame(rng, per_zone=3, order="closest")
    plain = _target_frame(rng, with_status=False)
    plain_single = ZoneFrame(mean_m=plain.mean_m, sigma_m=plain.sigma_m, valid=plain.valid,
                             no_target=np.where(plain.valid, False, True))
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_zone_frame("/tof/zones", 1_000, "tof", frame)
        writer.add_zone_frame("/tof/zones", 2_000, "tof", plain)
        writer.add_zone_frame("/tof/zones", 3_000, "tof", plain_single)  # written with T = 1
        writer.add_zone_frame("/tof/single", 1_000, "tof", plain_single)
        with pytest.raises(ValueError, match=r"topic /tof/single carries deltar_msgs/msg/"
                                             r"ZoneFrame \(one target per zone\)"):
            writer.add_zone_frame("/tof/single", 2_000, "tof", frame)
    messages = read_messages(tmp_path / "bag", "/tof/zones")
    assert [type(msg).__name__ for _, msg in messages] == [
        "deltar_msgs__msg__MultiTargetZoneFrame"] * 3
    first, second, third = (zone_frame_from_msg(msg) for _, msg in messages)
    _assert_same_targets(first, frame)
    np.testing.assert_array_equal(first.target_status, frame.target_status)
    _assert_same_targets(second, plain)
    assert third.targets_per_zone == 1
    np.testing.assert_array_equal(third.target_valid[..., 0], plain_single.valid)
    np.testing.assert_array_equal(third.no_target, plain_single.no_target)
    (_, single), = read_messages(tmp_path / "bag", "/tof/single")
    assert not hasattr(single, "target_distance_m")
    assert zone_frame_from_msg(single).target_mean_m is None
