"""Reading ROS 2 bags: camera + CameraInfo + ToF paired, predicted into depth bags.

Input bags are written here with ``rosbags`` directly (not with deltar's writer), read
by ``deltar replay --bag``; outputs are read back with ``rosbags``' own reader.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.camera import CameraIntrinsics
from deltar.capture.bag_replay import pair_calibration, replay_bag_to_bag
from deltar.cli.main import app
from deltar.inference.estimator import DepthEstimator
from deltar.io.ros_messages import metric_image_from_msg, typestore
from deltar.io.rosbag_reader import BagInput
from tests.inference.fakes import ZonePainterNet

runner = CliRunner(env={"COLUMNS": "200"})
HEIGHT, WIDTH = 48, 64
INTR = CameraIntrinsics(52.0, 52.0, 31.5, 23.5, WIDTH, HEIGHT)
T0 = 1_700_000_000_000_000_000  # a wall-clock stamp, ns


def _header(store, stamp_ns, frame_id):
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
        frame_id=frame_id)


def _image(store, stamp, encoding="rgb8", seed=0):
    rgb = np.random.default_rng(seed).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    if encoding == "compressed":
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        return rgb, "sensor_msgs/msg/CompressedImage", store.types[
            "sensor_msgs/msg/CompressedImage"](header=_header(store, stamp, "cam_optical"),
                                               format="png", data=png.reshape(-1))
    data = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "mono8": rgb[..., :1]}[encoding]
    channels = data.shape[2]
    return rgb, "sensor_msgs/msg/Image", store.types["sensor_msgs/msg/Image"](
        header=_header(store, stamp, "cam_optical"), height=HEIGHT, width=WIDTH,
        encoding=encoding, is_bigendian=0, step=channels * WIDTH,
        data=np.ascontiguousarray(data).reshape(-1))


def _camera_info(store, stamp):
    intr = INTR
    roi = store.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                          width=0, do_rectify=False)
    return store.types["sensor_msgs/msg/CameraInfo"](
        header=_header(store, stamp, "cam_optical"), height=HEIGHT, width=WIDTH,
        distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)


def _zones(store, stamp, seed=0):
    rng = np.random.default_rng(100 + seed)
    distance = rng.uniform(0.8, 3.0, 64).astype(np.float32)
    status = np.full(64, 5, np.uint8)
    status[[7, 20]] = 255  # no target
    msg = store.types["deltar_msgs/msg/ZoneFrame"](
        header=_header(store, stamp, "tof"), sensor_model="VL53L5CX", zone_count=64,
        distance_m=distance, sigma_m=np.full(64, 0.02, np.float32), status=status,
        valid=np.zeros(0, bool), hist_edges_m=np.zeros(0, np.float32),
        hist_counts=np.zeros(0, np.float32))
    return distance, status, msg


def write_input_bag(path: Path, frames: int = 3, *, encoding: str = "rgb8",
                    tof_offset_ns: int | list[int] = 4_000_000, with_tof: bool = True,
                    with_info: bool = True, storage=StoragePlugin.SQLITE3) -> dict:
    """A camera at 10 Hz with CameraInfo and a ToF frame 4 ms (or as given) after each image."""
    store = typestore()
    offsets = tof_offset_ns if isinstance(tof_offset_ns, list) else [tof_offset_ns] * frames
    truth = {"rgb": [], "distance": [], "status": [], "stamps": []}
    with Writer(path, version=8, storage_plugin=storage) as writer:
        _, image_type, _ = _image(store, 0, encoding)
        cam = writer.add_connection("/camera/image", image_type, typestore=store)
        info = writer.add_connection("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                                     typestore=store) if with_info else None
        tof = writer.add_connection("/tof/zones", "deltar_msgs/msg/ZoneFrame",
                                    typestore=store) if with_tof else None
        for i in range(frames):
            stamp = T0 + i * 100_000_000
            rgb, msgtype, msg = _image(store, stamp, encoding, seed=i)
            writer.write(cam, stamp + 1000, store.serialize_cdr(msg, msgtype))
            if info is not None:
                writer.write(info, stamp + 1000, store.serialize_cdr(
                    _camera_info(store, stamp), "sensor_msgs/msg/CameraInfo"))
            if tof is not None:
                distance, status, zmsg = _zones(store, stamp + offsets[i], seed=i)
                writer.write(tof, stamp + offsets[i] + 1000,
                             store.serialize_cdr(zmsg, "deltar_msgs/msg/ZoneFrame"))
                truth["distance"].append(distance)
                truth["status"].append(status)
            truth["rgb"].append(rgb)
            truth["stamps"].append(stamp)
    return truth


def read_topic(path: Path, topic: str) -> list[tuple[int, object]]:
    """Messages of a topic with rosbags' reader, types taken from the bag itself."""
    with AnyReader([path]) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        assert connections, f"no topic {topic} in {[c.topic for c in reader.connections]}"
        return [(t, reader.deserialize(raw, c.msgtype))
                for c, t, raw in reader.messages(connections=connections)]


def _digest(folder: Path) -> dict:
    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "compressed"])
def test_bag_pairs_decode_and_predict_into_a_new_bag(tmp_path, encoding):
    source = tmp_path / "in_bag"
    truth = write_input_bag(source, encoding=encoding)
    before = _digest(source)
    bag = BagInput(source)
    assert (bag.image_topic, bag.info_topic, bag.tof_topic) == \
        ("/camera/image", "/camera/camera_info", "/tof/zones")
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    out, frames = replay_bag_to_bag(bag, estimator, tmp_path / "out_bag", points=True)
    assert frames == 3
    assert _digest(source) == before  # the input bag is untouched
    depth_msgs = read_topic(out, "/deltar/depth")
    info_msgs = read_topic(out, "/deltar/camera_info")
    unc_msgs = read_topic(out, "/deltar/uncertainty")
    cloud_msgs = read_topic(out, "/deltar/points")
    assert len(depth_msgs) == len(info_msgs) == len(unc_msgs) == len(cloud_msgs) == 3
    for i, ((log_ns, depth_msg), (_, info), (_, unc)) in enumerate(
            zip(depth_msgs, info_msgs, unc_msgs, strict=True)):
        stamp = truth["stamps"][i]
        assert log_ns == stamp + 1000  # the camera image's bag time
        for msg in (depth_msg, info, unc):
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
            assert msg.header.frame_id == "cam_optical"
        assert depth_msg.encoding == "32FC1" and depth_msg.step == 4 * WIDTH
        depth = metric_image_from_msg(depth_msg)
        assert depth.shape == (HEIGHT, WIDTH)
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), INTR.matrix)
        # The bag holds the prediction for the decoded image and the zone frame, with
        # NaN where the network gives no depth (REP 118).
        pair = BagInput(source).pairs()[i]
        frame = pair.zone_frame
        valid = np.isin(truth["status"][i], (5, 9))
        np.testing.assert_array_equal(frame.valid.reshape(-1), valid)
        np.testing.assert_allclose(frame.mean_m.reshape(-1)[valid],
                                   truth["distance"][i][valid])
        expected = estimator.predict(truth["rgb"][i], frame, pair_calibration(pair, None))
        has_depth = expected.depth_m > 0
        np.testing.assert_array_equal(np.isnan(depth), ~has_depth)
        np.testing.assert_allclose(depth[has_depth], expected.depth_m[has_depth])
        uncertainty = metric_image_from_msg(unc)
        np.testing.assert_allclose(uncertainty[has_depth], 0.1, atol=1e-6)
        assert np.isnan(uncertainty[~has_depth]).all()


def test_missing_tof_topic_is_a_clear_error(tmp_path):
    write_input_bag(tmp_path / "bag", with_tof=False)
    with pytest.raises(ValueError, match=r"no ToF topic \(deltar_msgs/msg/ZoneFrame or "
                       r"deltar_msgs/msg/MultiTargetZoneFrame\)"):
        BagInput(tmp_path / "bag")
    with pytest.raises(ValueError, match="no topic '/nope'"):
        BagInput(tmp_path / "bag", tof_topic="/nope")
    with pytest.raises(ValueError, match="is sensor_msgs/msg/Image, expected"):
        BagInput(tmp_path / "bag", tof_topic="/camera/image")
    result = runner.invoke(app, ["replay", "--bag", str(tmp_path / "bag"), "--out-bag",
                                 str(tmp_path / "o")])
    assert result.exit_code == 1 and "no ToF topic" in result.output
    assert not (tmp_path / "o").exists()


def test_wrong_encoding_names_topic_and_encoding(tmp_path):
    write_input_bag(tmp_path / "bag", encoding="mono8")
    bag = BagInput(tmp_path / "bag")
    with pytest.raises(ValueError, match=r"/camera/image: image encoding 'mono8' is not "
                                         r"supported; expected rgb8 or bgr8"):
        replay_bag_to_bag(bag, DepthEstimator(ZonePainterNet()), tmp_path / "out")
    assert not (tmp_path / "out").exists()  # nothing half written
    assert not list(tmp_path.glob(".out.*"))


def test_unpaired_stamps_are_a_clear_error(tmp_path):
    write_input_bag(tmp_path / "bag", tof_offset_ns=5_000_000_000)
    with pytest.raises(ValueError, match=r"no ToF message on /tof/zones has a camera image "
                                         r"within 0.02 s"):
        BagInput(tmp_path / "bag").pairs()
    with pytest.warns(UserWarning, match="2 of 3 ToF frames share a colour image"):
        pairs = BagInput(tmp_path / "bag").pairs(tolerance_s=6.0)
    assert [p.image_index for p in pairs] == [2]  # all three nearest the last image


def test_partly_unpaired_stamps_warn_and_skip(tmp_path):
    # The second ToF frame is 50 ms from both neighbouring images (10 Hz camera).
    write_input_bag(tmp_path / "bag", tof_offset_ns=[4_000_000, 50_000_000, 4_000_000])
    with pytest.warns(UserWarning, match="skipped 1 of 3 ToF frames"):
        pairs = BagInput(tmp_path / "bag").pairs()
    assert [p.image_index for p in pairs] == [0, 2]
    assert all(abs(p.offset_s + 0.004) < 1e-6 for p in pairs)  # float64 s of a 1.7e9 s clock


def test_no_camera_info_needs_a_calibration(tmp_path):
    write_input_bag(tmp_path / "bag", with_info=False)
    bag = BagInput(tmp_path / "bag")
    assert bag.info_topic is None
    with pytest.raises(ValueError, match="no sensor_msgs/msg/CameraInfo topic; pass a rig "
                                         "calibration"):
        replay_bag_to_bag(bag, DepthEstimator(ZonePainterNet()), tmp_path / "out")


def test_vl53l5cx_ros2_bag_replays_with_its_topic_named(tmp_path):
    store = typestore()
    path = tmp_path / "bag"
    with Writer(path, version=8) as writer:
        cam = writer.add_connection("/camera/image", "sensor_msgs/msg/Image", typestore=store)
        info = writer.add_connection("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                                     typestore=store)
        tof = writer.add_connection("/vl53l5cx/x29/image", "sensor_msgs/msg/Image",
                                    typestore=store)
        for i in range(2):
            stamp = T0 + i * 100_000_000
            _, msgtype, msg = _image(store, stamp, seed=i)
            writer.write(cam, stamp, store.serialize_cdr(msg, msgtype))
            writer.write(info, stamp, store.serialize_cdr(_camera_info(store, stamp),
                                                          "sensor_msgs/msg/CameraInfo"))
            dist = np.full((8, 8), 1.25, "<f4")
            tmsg = store.types["sensor_msgs/msg/Image"](
                header=_header(store, stamp + 2_000_000, "tof"), height=8, width=8,
                encoding="32FC1", is_bigendian=0, step=32, data=dist.view(np.uint8).reshape(-1))
            writer.write(tof, stamp + 2_000_000, store.serialize_cdr(tmsg, "sensor_msgs/msg/Image"))
    with pytest.raises(ValueError, match="needs the ToF topic named"):
        BagInput(path, tof_format="vl53l5cx_ros2")
    bag = BagInput(path, tof_format="vl53l5cx_ros2", tof_topic="/vl53l5cx/x29/image")
    assert bag.image_topic == "/camera/image"  # the ToF image is not taken for the camera
    pairs = bag.pairs()
    assert len(pairs) == 2 and np.allclose(pairs[0].zone_frame.mean_m, 1.25)
    with pytest.raises(ValueError, match="no ToF topic"):
        BagInput(path)  # the default format wants a deltar_msgs/msg/ZoneFrame topic
    result = runner.invoke(app, ["replay", "--bag", str(path), "--tof-format", "vl53l5cx_ros2",
                                 "--tof-topic", "/vl53l5cx/x29/image", "--preset",
                                 "deltar-lite", "--out-bag", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert len(read_topic(tmp_path / "out", "/deltar/depth")) == 2


def test_missing_rosbags_names_the_extra(tmp_path, monkeypatch):
    write_input_bag(tmp_path / "bag", frames=1)
    monkeypatch.setitem(__import__("sys").modules, "rosbags", None)
    monkeypatch.setitem(__import__("sys").modules, "rosbags.rosbag2", None)
    with pytest.raises(ImportError, match=r'pip install "deltar\[ros\]"'):
        BagInput(tmp_path / "bag")
    result = runner.invoke(app, ["replay", "--bag", str(tmp_path / "bag"), "--preset",
                                 "deltar-lite", "--out-bag", str(tmp_path / "out")])
    assert result.exit_code == 1 and 'needs the "ros" extra' in result.output


def _depth_bag(path: Path, depth_shape=(HEIGHT, WIDTH), missing: int = 1,
               late_ns: int = 5000) -> list[np.ndarray]:
    """Camera + ToF as :func:`write_input_bag` and a RealSense-style 16UC1 depth topic,
    its message logged before the image for odd frames, ``late_ns`` after it for even
    ones, and absent for frame ``missing``."""
    store = typestore()
    truths = []
    with Writer(path, version=8) as writer:
        cam = writer.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image",
                                    typestore=store)
        info = writer.add_connection("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo",
                                     typestore=store)
        tof = writer.add_connection("/tof/zones", "deltar_msgs/msg/ZoneFrame", typestore=store)
        depth = writer.add_connection("/camera/aligned_depth_to_color/image_raw",
                                      "sensor_msgs/msg/Image", typestore=store)
        for i in range(4):
            stamp = T0 + i * 100_000_000
            millimetres = np.full(depth_shape, 1000 + 250 * i, np.uint16)
            millimetres[0, :5] = 0  # no return
            truths.append(np.where(millimetres > 0, millimetres / 1000.0, 0.0))
            depth_msg = store.types["sensor_msgs/msg/Image"](
                header=_header(store, stamp + 2_000_000, "cam_optical"), height=depth_shape[0],
                width=depth_shape[1], encoding="16UC1", is_bigendian=0, step=2 * depth_shape[1],
                data=millimetres.view(np.uint8).reshape(-1))
            depth_log = stamp + (-500 if i % 2 else late_ns)
            if i != missing:
                writer.write(depth, depth_log, store.serialize_cdr(depth_msg,
                                                                   "sensor_msgs/msg/Image"))
            _, msgtype, msg = _image(store, stamp, seed=i)
            writer.write(cam, stamp + 1000, store.serialize_cdr(msg, msgtype))
            writer.write(info, stamp + 1000, store.serialize_cdr(_camera_info(store, stamp),
                                                                 "sensor_msgs/msg/CameraInfo"))
            _, _, zmsg = _zones(store, stamp + 4_000_000, seed=i)
            writer.write(tof, stamp + 4_001_000, store.serialize_cdr(
                zmsg, "deltar_msgs/msg/ZoneFrame"))
    return truths


def test_a_depth_topic_is_read_beside_the_images(tmp_path):
    truths = _depth_bag(tmp_path / "bag")
    assert BagInput(tmp_path / "bag").depth_topic is None  # not deltar's name: ask for it
    bag = BagInput(tmp_path / "bag", depth_topic="/camera/aligned_depth_to_color/image_raw")
    assert bag.image_topic == "/camera/color/image_raw"
    pairs = bag.pairs()
    indices = bag.depth_indices(pairs, tolerance_s=0.01)
    assert indices == [0, None, 1, 2]  # frame 1 has no depth message
    got = {p.image_index: (rgb, depth) for p, rgb, depth in bag.images_with_depth(pairs, indices)}
    assert sorted(got) == [0, 1, 2, 3]
    assert got[1][1] is None
    for i in (0, 2, 3):
        np.testing.assert_allclose(got[i][1], truths[i], atol=1e-6)
        assert got[i][1].dtype == np.float32 and got[i][0].shape == (HEIGHT, WIDTH, 3)
    assert bag.depth_indices(pairs, tolerance_s=0.001) == [None] * 4  # 2 ms apart
    with pytest.raises(ValueError, match="expected sensor_msgs/msg/Image"):
        BagInput(tmp_path / "bag", depth_topic="/tof/zones")
    _depth_bag(tmp_path / "small", depth_shape=(24, 32))
    small = BagInput(tmp_path / "small", depth_topic="/camera/aligned_depth_to_color/image_raw")
    with pytest.raises(ValueError, match="registered to the camera"):
        pairs = small.pairs()
        list(small.images_with_depth(pairs, small.depth_indices(pairs)))



def test_depth_logged_after_the_next_image_keeps_the_images_order(tmp_path):
    # Frame 0's depth is logged 150 ms late, after frame 1's image (which has none) and
    # frame 2's: every frame still comes out in the order of the images.
    _depth_bag(tmp_path / "bag", missing=1, late_ns=150_000_000)
    bag = BagInput(tmp_path / "bag", depth_topic="/camera/aligned_depth_to_color/image_raw")
    pairs = bag.pairs()
    indices = bag.depth_indices(pairs)
    plain = [p.image_index for p, _ in bag.images(pairs)]
    joined = [(p.image_index, d is None) for p, _, d in bag.images_with_depth(pairs, indices)]
    assert plain == [0, 1, 2, 3] and joined == [(0, False), (1, True), (2, False), (3, False)]
    auto = BagInput(tmp_path / "bag", depth_topic="auto")
    assert auto.depth_topic is None  # no topic of deltar record's name: none found


def test_a_repeated_tof_stamp_is_refused_naming_topic_and_stamp(tmp_path):
    # The second ToF message carries the first one's stamp (100 ms - 96 ms after T0 + 4).
    write_input_bag(tmp_path / "bag", tof_offset_ns=[4_000_000, -96_000_000, 4_000_000])
    with pytest.raises(ValueError, match=rf"2 messages on the ToF topic /tof/zones have "
                       rf"the header stamp {T0 + 4_000_000} ns"):
        BagInput(tmp_path / "bag").pairs()


def test_one_tof_frame_per_image_the_nearest(tmp_path):
    # ToF 1 lands 8 ms after image 0, nearer to it than to image 1: image 0 has two.
    write_input_bag(tmp_path / "bag", tof_offset_ns=[4_000_000, -92_000_000, 4_000_000])
    with pytest.warns(UserWarning, match=r"1 of 3 ToF frames share a colour image with a "
                      r"ToF frame nearer to it in time and are left out"):
        pairs = BagInput(tmp_path / "bag").pairs()
    assert [p.image_index for p in pairs] == [0, 2]
    assert [p.tof_stamp_ns for p in pairs] == [T0 + 4_000_000, T0 + 204_000_000]


def test_pairs_apply_the_time_offset(tmp_path):
    # The sensor's clock runs 300 ms behind the camera's.
    write_input_bag(tmp_path / "bag", tof_offset_ns=-300_000_000)
    bag = BagInput(tmp_path / "bag")
    with pytest.raises(ValueError, match=r"within 0.02 s .*check the header stamps, the "
                       "time offset"):
        bag.pairs()
    pairs = bag.pairs(time_offset_s=0.3)
    assert [p.image_index for p in pairs] == [0, 1, 2]
    assert all(p.offset_s == pytest.approx(0.3) for p in pairs)
