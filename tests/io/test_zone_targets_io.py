"""Several targets per zone through zone files, recordings and ROS 2 bags."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deltar.camera import CameraIntrinsics
from deltar.io.recording import Recording, RecordingMeta, RecordingWriter
from deltar.io.ros_messages import (
    MULTI_TARGET_ZONE_FRAME_MSGTYPE,
    ZONE_FRAME_MSGTYPE,
    zone_frame_from_msg,
)
from deltar.io.rosbag_reader import read_messages
from deltar.io.rosbag_writer import BagWriter
from deltar.io.zone_file import (
    load_zone_frame,
    save_zone_frame,
    zone_frame_from_dict,
    zone_frame_from_driver_result,
    zone_frame_to_dict,
)
from deltar.sensor.zone_frame import ZoneFrame

CAMERA = CameraIntrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)


def _target_frame(rng: np.random.Generator, grid: int = 8, per_zone: int = 3,
                  order: str = "strongest", with_status: bool = True,
                  timestamp_s: float = 12.25) -> ZoneFrame:
    zones = grid * grid
    valid = rng.random((zones, per_zone)) > 0.3
    mean = np.where(valid, rng.uniform(0.2, 3.9, (zones, per_zone)), 0.0)
    sigma = np.where(valid, rng.uniform(0.0, 0.1, (zones, per_zone)), 0.0)
    status = np.where(valid, 5, 255 * (rng.random((zones, per_zone)) > 0.5)).astype(np.uint8)
    return ZoneFrame(mean_m=mean[:, 0], sigma_m=sigma[:, 0], valid=valid[:, 0],
                     status=status[:, 0] if with_status else None, timestamp_s=timestamp_s,
                     sensor_model="VL53L8CX", target_mean_m=mean, target_sigma_m=sigma,
                     target_valid=valid, target_status=status if with_status else None,
                     target_order=order)


def _assert_same_targets(back: ZoneFrame, frame: ZoneFrame) -> None:
    assert back.targets_per_zone == frame.targets_per_zone
    assert back.target_order == frame.target_order
    np.testing.assert_array_equal(back.target_valid, frame.target_valid)
    np.testing.assert_allclose(back.target_mean_m, frame.target_mean_m, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.target_sigma_m, frame.target_sigma_m, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(back.valid, frame.valid)
    np.testing.assert_allclose(back.mean_m, frame.mean_m, atol=1e-6, rtol=0)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
@pytest.mark.parametrize("grid, per_zone, order", [(8, 3, "strongest"), (4, 2, "closest"),
                                                   (8, 1, "strongest")])
def test_zone_file_round_trip_keeps_every_target(tmp_path, rng, suffix, grid, per_zone, order):
    frame = _target_frame(rng, grid, per_zone, order)
    back = load_zone_frame(save_zone_frame(tmp_path / f"frame{suffix}", frame))
    _assert_same_targets(back, frame)
    np.testing.assert_array_equal(back.target_status, frame.target_status)


def test_single_target_files_are_unchanged_and_old_files_read(tmp_path, rng):
    frame = _target_frame(rng)
    single = ZoneFrame(mean_m=frame.mean_m, sigma_m=frame.sigma_m, valid=frame.valid,
                       status=frame.status, timestamp_s=frame.timestamp_s,
                       sensor_model=frame.sensor_model)
    data = zone_frame_to_dict(single)
    assert sorted(data) == ["mean_m", "no_target", "schema", "schema_version", "sensor_model",
                            "sigma_m", "status", "timestamp_s", "valid", "zone_count"]
    # A file written before the target keys existed: no targets, T = 1 from the primary.
    path = tmp_path / "old.json"
    path.write_text(json.dumps(data))
    back = load_zone_frame(path)
    assert back.target_mean_m is None and back.targets_per_zone == 1
    np.testing.assert_array_equal(back.targets()[2][..., 0], frame.valid)
    # With targets, the extra keys and nothing else change.
    with_targets = zone_frame_to_dict(frame)
    assert {k: v for k, v in with_targets.items() if k in data} == data
    assert sorted(set(with_targets) - set(data)) == [
        "target_mean_m", "target_order", "target_sigma_m", "target_status", "target_valid",
        "targets_per_zone"]
    assert np.shape(with_targets["target_mean_m"]) == (64, 3)


@pytest.mark.parametrize("edit, message", [
    ({"target_valid": None}, r"target keys .* need \['target_valid'\]"),
    ({"targets_per_zone": None}, r"need \['targets_per_zone'\]"),
    ({"targets_per_zone": 5}, "targets_per_zone must be an integer in 1..4, got 5"),
    ({"targets_per_zone": 2}, r"target_mean_m must be \(64, 2\)"),
    ({"target_mean_m": [[1.0] * 3] * 63}, r"target_mean_m must be \(64, 3\)"),
    ({"target_sigma_m": [[-1.0] * 3] * 64}, "target_sigma_m has negative values"),
    ({"target_mean_m": [["1.0"] * 3] * 64}, "target_mean_m must hold numbers"),
    ({"target_valid": [["yes"] * 3] * 64}, "target_valid must hold 192 booleans"),
    ({"target_order": "nearest"}, "ZoneFrame.target_order must be one of"),
    ({"target_order": 3}, "target_order must be a string"),
], ids=["no-valid", "no-count", "count-5", "count-mismatch", "shape", "negative", "strings",
        "valid-strings", "order", "order-number"])
def test_bad_target_keys_name_the_file_and_key(tmp_path, rng, edit, message):
    data = zone_frame_to_dict(_target_frame(rng))
    data.update(edit)
    data = {k: v for k, v in data.items() if v is not None}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=message) as caught:
        load_zone_frame(path)
    assert str(path) in str(caught.value)


def test_driver_dumps_and_results_with_several_targets(tmp_path):
    distance = np.repeat(np.arange(16) * 100.0 + 500, 2)
    distance[1::2] += 1500
    dump = {"distance_mm": distance.tolist(), "range_sigma_mm": [10] * 32,
            "target_status": [5] * 32, "nb_target_detected": [2] * 15 + [1],
            "target_order": "closest"}
    path = tmp_path / "dump.json"
    path.write_text(json.dumps(dump))
    frame = load_zone_frame(path)
    assert frame.grid == 4 and frame.targets_per_zone == 2 and frame.target_order == "closest"
    assert frame.flat_targets()[2][:, 1].tolist() == [True] * 15 + [False]
    np.testing.assert_allclose(frame.flat_targets()[0][0], [0.5, 2.0], atol=1e-6)

    class Results:  # a driver's results object (attributes, as vl53l5cx-ctypes)
        def __init__(self) -> None:
            self.distance_mm = list(distance)
            self.range_sigma_mm = [10] * 32
            self.target_status = [5] * 32
            self.nb_target_detected = [1] * 16

    frame = zone_frame_from_driver_result(Results(), targets_per_zone=2)
    assert frame.targets_per_zone == 2 and not frame.target_valid[..., 1].any()
    with pytest.raises(ValueError, match=r"dump\.json: invalid driver output: target_order"):
        zone_frame_from_dict({**dump, "target_order": "nearest"}, source=str(path))


def test_recording_round_trip_keeps_the_targets(tmp_path, rng):
    writer = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    frames = [_target_frame(rng, grid=4, per_zone=2, timestamp_s=t) for t in (0.1, 0.2)]
    for frame in frames:
        writer.add_zone_frame(frame)
    for t in (0.1, 0.2):
        writer.add_color(t, np.zeros((24, 32, 3), np.uint8))
    pairs = Recording(tmp_path / "rec").pairs()
    assert len(pairs) == 2
    for pair, frame in zip(pairs, frames, strict=True):
        _assert_same_targets(pair.zone_frame, frame)


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
                      target_valid=np.zeros(0, bool))
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
    assert ZONE_FRAME_MSGTYPE != MULTI_TARGET_ZONE_FRAME_MSGTYPE
