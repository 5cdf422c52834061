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


#: MultiTargetZoneFrame as it was before ``target_signal`` (bags written then hold it).
PREVIOUS_MULTI_TARGET_MSG = """std_msgs/Header header
string sensor_model
uint16 zone_count
float32[] distance_m
float32[] sigma_m
uint8[] status
bool[] valid
float32[] hist_edges_m
float32[] hist_counts
uint8 targets_per_zone
string target_order
float32[] target_distance_m
float32[] target_sigma_m
uint8[] target_status
bool[] target_valid
"""


#: A later layout with a field this version does not know (read with the stored definition).
LATER_MULTI_TARGET_MSG = PREVIOUS_MULTI_TARGET_MSG + "float32[] target_signal\nuint16[] later\n"


def _layout_message(frame: ZoneFrame, definition: str):
    """``frame`` as a MultiTargetZoneFrame of another layout, and that layout's store."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from deltar.io.ros_messages import MULTI_TARGET_ZONE_FRAME_MSGTYPE as msgtype
    from deltar.io.ros_messages import stamped_header

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(definition, msgtype))
    mean, sigma, valid = frame.flat()
    t_mean, t_sigma, t_valid = frame.flat_targets()
    later = {} if definition == PREVIOUS_MULTI_TARGET_MSG else {
        "target_signal": frame.target_signal.reshape(-1), "later": np.arange(3, dtype=np.uint16)}
    msg = store.types[msgtype](
        header=stamped_header(5_000_000_000, "tof"), sensor_model=frame.sensor_model,
        zone_count=frame.zone_count, distance_m=np.where(valid, mean, np.nan).astype(np.float32),
        sigma_m=sigma.astype(np.float32), status=np.zeros(0, np.uint8), valid=valid,
        hist_edges_m=np.zeros(0, np.float32), hist_counts=np.zeros(0, np.float32),
        targets_per_zone=frame.targets_per_zone, target_order=frame.target_order,
        target_distance_m=np.where(t_valid, t_mean, np.nan).reshape(-1).astype(np.float32),
        target_sigma_m=t_sigma.reshape(-1).astype(np.float32),
        target_status=np.zeros(0, np.uint8), target_valid=t_valid.reshape(-1), **later)
    return store, msgtype, msg


@pytest.mark.parametrize("layout, stored_definition", [
    ("previous", True), ("previous", False), ("later", True)],
    ids=["previous-definition-in-bag", "previous-no-definition", "later-definition-in-bag"])
def test_bags_of_other_layouts_read_with_their_definition(tmp_path, rng, layout,
                                                          stored_definition):
    from rosbags.rosbag2 import Writer

    frame = _target_frame(rng, per_zone=2, with_signal=layout == "later", with_status=False)
    new = _target_frame(rng, per_zone=2, timestamp_s=6.0)
    definition = PREVIOUS_MULTI_TARGET_MSG if layout == "previous" else LATER_MULTI_TARGET_MSG
    store, msgtype, msg = _layout_message(frame, definition)
    with Writer(tmp_path / "bag", version=8) as writer:
        # Without a stored definition (as ROS 2 Humble's recorder writes bags), the
        # reader tries this package's layout, then the previous one.
        extra = {"typestore": store} if stored_definition else {"msgdef": "",
                                                                "rihs01": "RIHS01_" + "0" * 64}
        topic = writer.add_connection("/tof/zones", msgtype, **extra)
        writer.write(topic, 1, store.serialize_cdr(msg, msgtype))
    (_, message), = read_messages(tmp_path / "bag", "/tof/zones")
    back = zone_frame_from_msg(message)
    assert (back.target_signal is None) == (layout == "previous")
    _assert_same_targets(back, frame)
    # The current layout written by BagWriter keeps the signal.
    with BagWriter(tmp_path / "new") as writer:
        writer.add_zone_frame("/tof/zones", 6_000_000_000, "tof", new)
    (_, current), = read_messages(tmp_path / "new", "/tof/zones")
    _assert_same_targets(zone_frame_from_msg(current), new)


def test_a_stopped_replay_keeps_the_frames_written_and_an_error_keeps_none(tmp_path,
                                                                         monkeypatch):
    """Ctrl+C (or the CLI's SIGTERM) during ``replay --out-bag`` keeps a readable bag of the
    frames before it, whole; another error leaves no bag; a stop before any frame, none."""
    source = tmp_path / "in_bag"
    write_input_bag(source, frames=4)
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")

    def stop_after(count, error):
        seen = []

        def on_item(item):
            seen.append(item)
            if len(seen) == count:
                raise error
        return on_item

    out = tmp_path / "stopped"
    with pytest.warns(UserWarning, match="keeps the 2 frames"), pytest.raises(KeyboardInterrupt):
        replay_bag_to_bag(BagInput(source), estimator, out, points=True,
                          on_item=stop_after(2, KeyboardInterrupt()))
    for name in ("depth", "uncertainty", "camera_info", "points"):
        assert len(read_topic(out, f"/deltar/{name}")) == 2, name
    with pytest.raises(RuntimeError):
        replay_bag_to_bag(BagInput(source), estimator, tmp_path / "failed",
                          on_item=stop_after(2, RuntimeError("disk gone")))

    def stopped_in_the_network(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(estimator, "predict", stopped_in_the_network)
    with pytest.raises(KeyboardInterrupt):
        replay_bag_to_bag(BagInput(source), estimator, tmp_path / "at-once")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in_bag", "stopped"]


def test_a_bag_stopped_while_opening_or_before_its_first_message_leaves_nothing(
        tmp_path, monkeypatch):
    """A stop between the staging folder's creation and the writer's opening leaves no
    hidden folder; a recording bag closed without a message is not kept (an empty bag
    only blocks the next recording to that path)."""
    from rosbags.rosbag2 import Writer

    from deltar.camera import CameraIntrinsics
    from deltar.io.recording import RecordingMeta
    from deltar.io.rosbag_writer import BagRecordingWriter

    def stopped(self):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(Writer, "open", stopped)
        with pytest.raises(KeyboardInterrupt):
            BagWriter(tmp_path / "bag")
    assert list(tmp_path.iterdir()) == []
    meta = RecordingMeta(CameraIntrinsics(50.0, 50.0, 15.5, 11.5, 32, 24), grid=4)
    BagRecordingWriter(tmp_path / "rec_bag", meta).close()
    assert list(tmp_path.iterdir()) == []
    writer = BagRecordingWriter(tmp_path / "rec_bag", meta)
    writer.add_color(0.0, np.zeros((24, 32, 3), np.uint8))
    writer.close()
    assert [p.name for p in tmp_path.iterdir()] == ["rec_bag"]
