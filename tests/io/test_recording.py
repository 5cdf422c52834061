"""Recording folders: append-only writer, reader, timestamp pairing, clear errors."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from deltar.camera import CameraIntrinsics
from deltar.io.recording import Recording, RecordingMeta, RecordingWriter
from deltar.sensor.zone_frame import ZoneFrame
from tests.io.test_zone_file import _assert_same_targets, _target_frame

CAMERA = CameraIntrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)


def _zone_frame(t: float, value: float = 1.0) -> ZoneFrame:
    return ZoneFrame(np.full(16, value), np.full(16, 0.01), np.ones(16, bool), timestamp_s=t)


def _write(folder, zone_times, color_times, depth_times=()):
    writer = RecordingWriter(folder, RecordingMeta(CAMERA, grid=4))
    for t in zone_times:
        writer.add_zone_frame(_zone_frame(t, value=1.0 + t))
    for t in color_times:
        writer.add_color(t, np.full((24, 32, 3), int(t * 10) % 255, np.uint8))
    for t in depth_times:
        writer.add_depth(t, np.full((24, 32), 1.234, np.float32))
    return writer


def test_pairs_take_the_nearest_images_within_tolerance(tmp_path):
    _write(tmp_path / "rec", zone_times=[0.0, 0.1, 0.2, 0.3],
           color_times=[0.005, 0.098, 0.25, 0.31], depth_times=[0.004, 0.2])
    rec = Recording(tmp_path / "rec")
    with pytest.warns(UserWarning, match="skipped 1 of 4"):
        pairs = rec.pairs(tolerance_s=0.02)
    # 0.2 has no colour within 20 ms (nearest 0.25) and is skipped.
    assert [p.zone_frame.timestamp_s for p in pairs] == [0.0, 0.1, 0.3]
    assert [round(p.color_offset_s, 3) for p in pairs] == [0.005, -0.002, 0.01]
    assert pairs[0].depth_path is not None and pairs[0].depth_path.stem == "4000000"
    assert pairs[1].depth_path is None  # nearest depth (0.004) is 96 ms away
    assert pairs[1].load_color().shape == (24, 32, 3)
    assert pairs[0].load_color()[0, 0, 0] == 0  # colour at 0.005 s was filled with 0
    depth = pairs[0].load_depth()
    assert depth.dtype == np.float32 and depth[0, 0] == pytest.approx(1.234)
    assert pairs[2].zone_frame.mean_m[0, 0] == pytest.approx(1.3)
    color, with_depth = pairs[0].load_images()
    np.testing.assert_array_equal(color, pairs[0].load_color())
    np.testing.assert_array_equal(with_depth, depth)
    assert pairs[1].load_images()[1] is None


def test_meta_and_layout_on_disk(tmp_path):
    _write(tmp_path / "rec", [1.0], [1.0], [1.0])
    meta = json.loads((tmp_path / "rec" / "meta.json").read_text())
    assert meta["schema_version"] == 1 and meta["grid"] == 4
    assert meta["intrinsics"]["fx"] == 50.0
    assert (tmp_path / "rec" / "color" / "1000000000.png").is_file()
    assert (tmp_path / "rec" / "depth" / "1000000000.png").is_file()
    lines = (tmp_path / "rec" / "zones.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["timestamp_s"] == 1.0


def test_writer_appends_but_never_overwrites(tmp_path):
    writer = _write(tmp_path / "rec", [0.0], [0.0])
    with pytest.raises(FileExistsError):
        writer.add_color(0.0, np.zeros((24, 32, 3), np.uint8))
    with pytest.raises(ValueError, match="not after"):
        writer.add_zone_frame(_zone_frame(0.0))
    # Reopening appends to the same recording.
    again = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    again.add_zone_frame(_zone_frame(0.5))
    with pytest.raises(ValueError, match="not after"):
        again.add_zone_frame(_zone_frame(0.2))
    assert len(Recording(tmp_path / "rec").zone_frames()) == 2
    other = CameraIntrinsics(60.0, 60.0, 15.5, 11.5, 32, 24)
    with pytest.raises(ValueError, match=r"has another intrinsics \(another rig\)"):
        RecordingWriter(tmp_path / "rec", RecordingMeta(other, grid=4))
    with pytest.raises(ValueError, match=r"has another sensor_model, grid \(another rig\)"):
        RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, sensor_model="VL53L8CX",
                                                        grid=8))


def test_writer_refuses_a_folder_of_other_files_and_takes_an_empty_one(tmp_path):
    data_set = tmp_path / "rgbd"
    (data_set / "color").mkdir(parents=True)
    (data_set / "color" / "000000.png").write_bytes(b"a real frame")
    with pytest.raises(FileExistsError, match="rgbd is not empty and holds no recording"):
        RecordingWriter(data_set, RecordingMeta(CAMERA, grid=4))
    assert sorted(p.name for p in data_set.rglob("*")) == ["000000.png", "color"]
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / ".hidden").write_text("")  # e.g. a file manager's; not a frame
    RecordingWriter(empty, RecordingMeta(CAMERA, grid=4))
    assert (empty / "meta.json").is_file()


def test_poses_are_written_by_time_and_the_end_time_covers_every_item(tmp_path):
    from deltar.io.pose_file import read_pose_file

    writer = _write(tmp_path / "rec", [0.5, 2.25], [0.5, 1.0], [1.5])
    pose = np.eye(4)
    pose[:3, 3] = (0.1, -0.2, 1.5)
    path = writer.add_pose(1.0, pose)
    assert path == tmp_path / "rec" / "pose" / "1000000000.txt"
    np.testing.assert_allclose(read_pose_file(path), pose)
    with pytest.raises(FileExistsError):
        writer.add_pose(1.0, np.eye(4))
    with pytest.raises(ValueError, match="not a rotation"):
        writer.add_pose(2.0, np.diag([2.0, 1.0, 1.0, 1.0]))
    # The latest of colour (1.0), depth (1.5) and zones (2.25).
    assert Recording(tmp_path / "rec").end_time_s() == pytest.approx(2.25)
    _write(tmp_path / "depth_last", [0.5], [0.5], [3.0])
    assert Recording(tmp_path / "depth_last").end_time_s() == pytest.approx(3.0)
    RecordingWriter(tmp_path / "empty", RecordingMeta(CAMERA, grid=4))
    assert Recording(tmp_path / "empty").end_time_s() is None


def test_appending_after_an_interrupted_line_keeps_the_recording_readable(tmp_path):
    folder = tmp_path / "rec"
    _write(folder, [0.1, 0.2, 0.3], [0.1])
    zones = folder / "zones.jsonl"
    whole = zones.read_bytes()
    cut = whole[:-40]  # the last append interrupted mid-line
    zones.write_bytes(cut)
    with pytest.warns(UserWarning, match="last line was cut off"):
        writer = RecordingWriter(folder, RecordingMeta(CAMERA, grid=4))
    writer.add_zone_frame(_zone_frame(0.4))
    times = [f.timestamp_s for f in Recording(folder).zone_frames()]
    assert times == [0.1, 0.2, 0.4]
    (kept,) = folder.glob("zones.jsonl.partial-*")  # every byte of the cut line kept
    assert cut[cut.rfind(b"\n") + 1:] == kept.read_bytes()
    # A last line that is complete but for its newline is kept as a reading.
    zones.write_bytes(zones.read_bytes()[:-1])
    RecordingWriter(folder, RecordingMeta(CAMERA, grid=4)).add_zone_frame(_zone_frame(0.5))
    assert [f.timestamp_s for f in Recording(folder).zone_frames()] == [0.1, 0.2, 0.4, 0.5]


def test_a_depth_map_in_the_colour_folder_is_refused_by_name(tmp_path):
    import cv2

    _write(tmp_path / "rec", [1.0], [1.0], [1.0])
    rec = Recording(tmp_path / "rec")
    (pair,) = rec.pairs()
    assert pair.load_color().shape == (24, 32, 3)
    cv2.imwrite(str(pair.color_path), np.full((24, 32), 1234, np.uint16))
    with pytest.raises(ValueError, match=r"1000000000.png: a single-channel uint16 image "
                       r"\(a depth map\?\), not an 8-bit colour image"):
        pair.load_color()
    # A 16-bit colour photo is no depth map: it is said to need 8 bits per channel.
    cv2.imwrite(str(pair.color_path), np.full((24, 32, 3), 1234, np.uint16))
    with pytest.raises(ValueError, match=r"1000000000.png: a 3-channel uint16 image; a "
                       r"colour image must be 8-bit RGB \(convert it, e.g. image >> 8 for "
                       r"16 bits per channel\)$") as caught:
        pair.load_color()
    assert "depth map" not in str(caught.value)
    cv2.imwrite(str(pair.color_path), np.full((24, 32), 7, np.uint8))  # 8-bit grey: fine
    np.testing.assert_array_equal(pair.load_color(), np.full((24, 32, 3), 7, np.uint8))


def test_writer_rejects_wrong_image_size(tmp_path):
    writer = _write(tmp_path / "rec", [], [])
    with pytest.raises(ValueError, match="image_rgb"):
        writer.add_color(1.0, np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match="depth_m"):
        writer.add_depth(1.0, np.full((24, 32), np.nan))


@pytest.mark.parametrize("times", [[0.0, 0.2, 0.1], [0.0, 0.1, 0.1]])
def test_unsorted_or_duplicate_timestamps_name_the_file(tmp_path, times):
    _write(tmp_path / "rec", [], [0.0])
    from deltar.io.zone_file import zone_frame_to_dict

    lines = [json.dumps(zone_frame_to_dict(_zone_frame(t))) for t in times]
    (tmp_path / "rec" / "zones.jsonl").write_text("\n".join(lines) + "\n")
    kind = "duplicate" if times[1] == times[2] else "unsorted"
    with pytest.raises(ValueError, match=rf"zones.jsonl:3: {kind} timestamp"):
        Recording(tmp_path / "rec").pairs()


def test_truncated_last_line_is_skipped_with_a_warning(tmp_path):
    _write(tmp_path / "rec", [0.0, 0.1], [0.0])
    with open(tmp_path / "rec" / "zones.jsonl", "a") as handle:
        handle.write('{"schema": "deltar.zone_fr')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = Recording(tmp_path / "rec").zone_frames()
    assert len(frames) == 2
    assert any("truncated" in str(w.message) for w in caught)


def test_missing_pieces_raise_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        Recording(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"meta\.json"):
        Recording(tmp_path / "empty")
    _write(tmp_path / "rec", [0.0], [])
    with pytest.raises(FileNotFoundError, match="no colour images"):
        Recording(tmp_path / "rec").pairs()
    (tmp_path / "rec" / "meta.json").write_text("{broken")
    with pytest.raises(ValueError, match=r"meta\.json: corrupt JSON"):
        Recording(tmp_path / "rec")


def test_pairs_apply_a_time_offset(tmp_path):
    """The camera's stamps run 50 ms ahead: zone t pairs with the image at t + 0.05."""
    _write(tmp_path / "rec", zone_times=[0.0, 0.1, 0.2], color_times=[0.02, 0.05, 0.12, 0.15,
                                                                      0.22, 0.25])
    rec = Recording(tmp_path / "rec")
    plain = rec.pairs(tolerance_s=0.03)
    shifted = rec.pairs(tolerance_s=0.03, time_offset_s=0.05)
    assert [round(p.color_offset_s, 3) for p in plain] == [0.02, 0.02, 0.02]
    assert [round(p.color_offset_s, 3) for p in shifted] == [0.05, 0.05, 0.05]
    with pytest.raises(ValueError, match="time_offset_s must be finite"):
        rec.pairs(time_offset_s=float("nan"))


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


def test_a_bag_or_an_empty_folder_is_no_recording_and_a_bag_is_named_so(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"recording has no meta\.json") as info:
        Recording(tmp_path / "empty")
    assert "ROS 2 bag" not in str(info.value)
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    with pytest.raises(FileNotFoundError, match="a ROS 2 bag, not a recording folder"):
        Recording(tmp_path / "bag")


def test_an_interrupted_writes_temporaries_are_no_frames(tmp_path):
    """A SIGTERM or SIGKILL during an atomic write leaves its hidden temporary beside the
    frames: the recording still reads, appends and gives its poses."""
    from deltar.mapping.poses import read_pose_folder

    writer = _write(tmp_path / "rec", [0.0, 0.1], [0.0, 0.1], [0.0, 0.1])
    writer.add_pose(0.0, np.eye(4))
    rec = tmp_path / "rec"
    for folder, name in (("color", ".200000000.png.i6bdqh8g.tmp.png"),
                         ("depth", ".200000000.png.x1y2z3.tmp.png"),
                         ("pose", ".200000000.txt.abcdef.tmp.txt")):
        (rec / folder / name).write_bytes(b"partial")
    pairs = Recording(rec).pairs(tolerance_s=0.02)
    assert len(pairs) == 2 and pairs[1].load_images()[1] is not None
    assert read_pose_folder(rec / "pose").names == ("0",)
    RecordingWriter(rec, RecordingMeta(CAMERA, grid=4)).add_color(
        0.3, np.zeros((24, 32, 3), np.uint8))
    assert len(Recording(rec).color_times_s) == 3


def test_a_frame_the_reader_would_refuse_is_not_written(tmp_path):
    """Millimetres written as metres would make the whole recording unreadable."""
    writer = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    writer.add_zone_frame(_zone_frame(1.0))
    with pytest.raises(ValueError, match=r"refusing to write a zone frame its reader would "
                       r"refuse: 16 valid zone\(s\) read distances outside"):
        writer.add_zone_frame(_zone_frame(2.0, value=2000.0))
    with pytest.raises(ValueError, match="frame must be a ZoneFrame, got dict"):
        writer.add_zone_frame({"mean_m": [1.0] * 16})
    writer.add_zone_frame(_zone_frame(3.0))
    assert [f.timestamp_s for f in Recording(tmp_path / "rec").zone_frames()] == [1.0, 3.0]


def test_metadata_the_reader_would_refuse_is_not_made():
    for changes, message in (({"grid": 5}, "grid must be 4 or 8, got 5"),
                             ({"fov_deg": (float("nan"), 45.0)}, "fov_deg must be two angles")):
        with pytest.raises(ValueError, match=message):
            RecordingMeta(CAMERA, **changes)
    assert RecordingMeta(CAMERA, fov_deg=(np.float32(45.0), 45)).grid == 8


def test_depth_is_the_one_of_the_paired_colour_image_not_of_another_camera_frame(tmp_path):
    """Depth is aligned to colour: a zone frame between two camera frames gets the colour
    image nearest it and that image's depth map, never the depth of the next camera frame
    (here the colour image at 33 ms has none; the depth at 66 ms is 18 ms from the zone
    frame but belongs to another image)."""
    _write(tmp_path / "rec", zone_times=[0.048], color_times=[0.0, 0.033, 0.066],
           depth_times=[0.0, 0.066])
    (pair,) = Recording(tmp_path / "rec").pairs(tolerance_s=0.02)
    assert pair.color_path.stem == "33000000"
    assert pair.depth_path is None
    # Depth stamped a little off its colour image (an RGB-D camera's two streams) pairs.
    _write(tmp_path / "rgbd", zone_times=[0.05], color_times=[0.0, 0.04],
           depth_times=[0.001, 0.041])
    (pair,) = Recording(tmp_path / "rgbd").pairs(tolerance_s=0.02)
    assert (pair.color_path.stem, pair.depth_path.stem) == ("40000000", "41000000")


def test_two_writers_on_one_folder_never_make_it_unreadable(tmp_path):
    """Each writer knew only its own last frame: a second writer (a recording started
    again while the first still runs) appended a frame older than the first writer's
    newest, and the whole recording then failed to read ('unsorted timestamp')."""
    first = _write(tmp_path / "rec", [1.0], [])
    second = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    first.add_zone_frame(_zone_frame(2.0))
    with pytest.raises(ValueError, match=r"zone frame timestamp 1.5 is not after the "
                       r"previous one \(2.0\)"):
        second.add_zone_frame(_zone_frame(1.5))
    second.add_zone_frame(_zone_frame(2.5))
    with pytest.raises(ValueError, match="not after"):
        first.add_zone_frame(_zone_frame(2.25))
    assert [f.timestamp_s for f in Recording(tmp_path / "rec").zone_frames()] == [1.0, 2.0,
                                                                                  2.5]


def test_appending_items_from_before_the_recordings_end_is_refused(tmp_path):
    """A rig whose clock started again (time.monotonic after a reboot) appended its first
    images among the old frames, where replay paired them with old zone frames, before
    its first zone frame was refused; now nothing stamped before the end is written."""
    _write(tmp_path / "rec", zone_times=[1.0, 2.0], color_times=[1.0, 2.0])
    again = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    for add in (lambda: again.add_color(1.5, np.zeros((24, 32, 3), np.uint8)),
                lambda: again.add_depth(1.5, np.ones((24, 32))),
                lambda: again.add_pose(2.0, np.eye(4))):
        with pytest.raises(ValueError, match=r"stamped 1.5 s|stamped 2.0 s"):
            add()
    rec = Recording(tmp_path / "rec")
    assert rec.color_times_s.tolist() == [1.0, 2.0] and rec.depth_paths == []
    assert not (tmp_path / "rec" / "pose").exists() or not any(
        (tmp_path / "rec" / "pose").iterdir())
    again.add_color(2.1, np.zeros((24, 32, 3), np.uint8))
    again.add_zone_frame(_zone_frame(2.1))
    assert len(Recording(tmp_path / "rec").pairs()) == 3


@pytest.mark.parametrize("time_s", [float("nan"), float("inf")])
def test_an_image_or_pose_at_a_time_that_is_no_number_is_refused_naming_it(tmp_path, time_s):
    writer = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    with pytest.raises(ValueError, match="timestamp_s must be a finite time in seconds, got"):
        writer.add_color(time_s, np.zeros((24, 32, 3), np.uint8))
    with pytest.raises(ValueError, match="timestamp_s must be a finite time in seconds"):
        writer.add_pose(time_s, np.eye(4))
    assert not any((tmp_path / "rec" / "color").iterdir())


def test_appending_zone_frames_on_a_sensor_clock_behind_the_camera_clock(tmp_path):
    """The sensor's stamps may run behind the camera's (time_offset_s, camera minus
    sensor clock): a recording appended to at its camera rate then has zone frames
    stamped before its last colour image, which is no clock that started again."""
    _write(tmp_path / "rec", zone_times=[0.9, 1.9], color_times=[1.0, 2.0])
    again = RecordingWriter(tmp_path / "rec", RecordingMeta(CAMERA, grid=4))
    again.add_color(2.1, np.zeros((24, 32, 3), np.uint8))
    again.add_zone_frame(_zone_frame(2.0))  # the sensor time of the colour image at 2.1
    assert len(Recording(tmp_path / "rec").pairs(time_offset_s=0.1)) == 3
    # A clock that started again is still refused, in either stream.
    with pytest.raises(ValueError, match="not after"):
        again.add_zone_frame(_zone_frame(0.5))
    with pytest.raises(ValueError, match="not after the end"):
        again.add_color(0.5, np.zeros((24, 32, 3), np.uint8))


def test_zone_frames_append_on_a_filesystem_without_flock(tmp_path, monkeypatch):
    """Some network mounts (NFS without lockd) answer flock with ENOLCK: the append is
    still checked against the file's last frame and written, not refused."""
    import errno

    from deltar.io import zone_lines

    class NoFlock:
        LOCK_EX = 2

        @staticmethod
        def flock(fd, op):
            raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(zone_lines, "fcntl", NoFlock)
    writer = _write(tmp_path / "rec", zone_times=[1.0], color_times=[])
    writer.add_zone_frame(_zone_frame(2.0))
    with pytest.raises(ValueError, match="not after"):
        writer.add_zone_frame(_zone_frame(1.5))
    assert [f.timestamp_s for f in Recording(tmp_path / "rec").zone_frames()] == [1.0, 2.0]
