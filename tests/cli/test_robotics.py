"""Robot-side commands end to end: ROS 2 bags in and out, rerun recordings of the views.

The bag and rerun helpers are the library tests' (tests/io/test_rosbag_reader.py,
tests/capture/test_viewer.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from deltar.capture.bag_replay import pair_calibration
from deltar.cli.main import app
from deltar.inference.loading import load_estimator
from deltar.io.ros_messages import image_from_msg, metric_image_from_msg
from deltar.io.rosbag_reader import BagInput
from tests.capture.test_viewer import _buffer, read_rrd
from tests.io.test_rosbag_reader import read_topic, write_input_bag

runner = CliRunner(env={"COLUMNS": "200"})


def test_cli_replay_bag_with_the_bundled_model(tmp_path):
    source = tmp_path / "in_bag"
    write_input_bag(source, frames=2)
    out = tmp_path / "depth_bag"
    result = runner.invoke(app, ["replay", "--bag", str(source), "--out-bag", str(out),
                                 "--bag-storage", "mcap"])
    assert result.exit_code == 0, result.output
    assert "wrote 2 frames" in result.output
    assert (out / "metadata.yaml").is_file() and list(out.glob("*.mcap"))
    depth_msgs = read_topic(out, "/deltar/depth")
    # The bag holds exactly what the estimator predicts for the same inputs.
    bag = BagInput(source)
    (pair, rgb), = list(bag.images(bag.pairs()[:1]))
    expected = load_estimator("default").predict(
        rgb, pair.zone_frame, pair_calibration(pair, None)).depth_m
    np.testing.assert_allclose(metric_image_from_msg(depth_msgs[0][1]), expected, atol=1e-5)
    again = runner.invoke(app, ["replay", "--bag", str(source), "--out-bag", str(out)])
    assert again.exit_code == 2 and "Invalid value for --out-bag" in again.output
    assert "exists; a bag is written whole into a new path" in again.output
    inside = runner.invoke(app, ["replay", "--bag", str(source), "--out-bag",
                                 str(source / "out")])
    assert inside.exit_code == 1 and "is inside the input" in inside.output


def test_cli_replay_bag_progress_counts_towards_the_frames_it_will_predict(tmp_path,
                                                                           monkeypatch):
    monkeypatch.setenv("DELTAR_PROGRESS_SECONDS", "0")  # a line per frame (not a terminal)
    source = tmp_path / "in_bag"
    write_input_bag(source, frames=3)
    result = runner.invoke(app, ["replay", "--bag", str(source), "--out-bag",
                                 str(tmp_path / "depth_bag"), "--every", "2"])
    assert result.exit_code == 0, result.output
    assert "wrote 2 frames" in result.output
    # Every second of the 3 pairs: 2 frames, the total known before the first.
    assert "replaying: 1/2 frames" in result.output
    assert "replaying: 2/2 frames" in result.output and "done in" in result.output


def test_record_writes_a_bag_that_replays(tmp_path):
    bag_path = tmp_path / "rec_bag"
    result = runner.invoke(app, ["record", str(bag_path), "--bag", "--simulate",
                                 "wall:1.5:6:48x64"])
    assert result.exit_code == 0, result.output
    assert "recorded 6 images, 3 zone frames" in result.output
    images = read_topic(bag_path, "/camera/color/image_raw")
    infos = read_topic(bag_path, "/camera/color/camera_info")
    depths = read_topic(bag_path, "/camera/depth/image")
    zones = read_topic(bag_path, "/tof/zones")
    assert (len(images), len(infos), len(depths), len(zones)) == (6, 6, 6, 3)
    assert images[0][1].encoding == "rgb8" and depths[0][1].encoding == "32FC1"
    np.testing.assert_allclose(metric_image_from_msg(depths[0][1]), 1.5, atol=1e-6)
    rgb = image_from_msg(images[1][1], "sensor_msgs/msg/Image")
    assert rgb.shape == (48, 64, 3)
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in images]
    np.testing.assert_allclose(np.diff(stamps), 1e9 / 30, atol=1)  # the 30 Hz camera
    zone_stamp = zones[0][1].header.stamp
    assert zone_stamp.sec * 10**9 + zone_stamp.nanosec == stamps[0] + 4_000_000
    assert zones[0][1].zone_count == 64
    # Simulated 4 cm bins: a wall at 1.5 m reads 1.5 m (bin centre 1.50).
    assert np.nanmedian(np.asarray(zones[0][1].distance_m)) == pytest.approx(1.5, abs=0.021)
    replayed = runner.invoke(app, ["replay", "--bag", str(bag_path), "--preset", "deltar-lite",
                                   "--out-bag", str(tmp_path / "depth")])
    assert replayed.exit_code == 0, replayed.output
    assert "wrote 3 frames" in replayed.output
    again = runner.invoke(app, ["record", str(bag_path), "--bag", "--simulate", "wall:1.5:2"])
    assert again.exit_code == 2 and "Invalid value for OUT" in again.output
    assert "with --bag the recording is a new bag" in again.output


def test_cli_record_simulate_and_predict_save_recordings(tmp_path):
    rrd = tmp_path / "rec.rrd"
    result = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate",
                                 "wall:1.2:4:48x64", "--rerun-save", str(rrd)])
    assert result.exit_code == 0, result.output
    rows = read_rrd(rrd)
    # Four camera frames at 30 Hz, each with the latest zone frame and the wall's depth.
    depth_rows = rows["/world/camera/image/depth"]
    assert len(depth_rows) == 4
    np.testing.assert_allclose(_buffer(depth_rows[0], "DepthImage"), 1.2, atol=1e-6)
    times = [r["time"] for r in rows["/world/camera/image/depth"]]
    np.testing.assert_allclose(times, np.arange(4) * 1e9 / 30, atol=1)
    zone_points = rows["/world/camera/tof/zones"]
    assert len(zone_points) == 4
    np.testing.assert_allclose(np.array(zone_points[0]["Points3D:positions"])[:, 2], 1.22,
                               atol=0.021)  # the simulator's 4 cm bins
    assert "/uncertainty" not in rows  # a recording has no prediction
    sample = tmp_path / "sample"
    from deltar.cli.demo import write_predict_sample
    from deltar.data.procedural import ProceduralReader
    from deltar.data.simulated import simulate_set

    simulate_set(ProceduralReader(1, 3, 48, 64), tmp_path / "scenes", scene="procedural")
    write_predict_sample(tmp_path / "scenes" / "data.json", sample)
    rrd2 = tmp_path / "pred.rrd"
    result = runner.invoke(app, ["predict", "--image", str(sample / "image.png"), "--zones",
                                 str(sample / "zones.json"), "--calib", str(sample / "calib.json"),
                                 "--out", str(tmp_path / "pred"), "--outputs", "npy",
                                 "--rerun-save", str(rrd2)])
    assert result.exit_code == 0, result.output
    rows = read_rrd(rrd2)
    saved = np.load(tmp_path / "pred" / "image_depth_m.npy")
    np.testing.assert_allclose(_buffer(rows["/world/camera/image/depth"][0], "DepthImage"), saved)
    # An existing viewer recording is refused by option name and kept.
    before = rrd2.read_bytes()
    again = runner.invoke(app, ["predict", "--image", str(sample / "image.png"), "--zones",
                                str(sample / "zones.json"), "--out", str(tmp_path / "pred2"),
                                "--outputs", "npy", "--rerun-save", str(rrd2)])
    assert again.exit_code == 2 and "--rerun-save" in again.output
    assert "random, untrained" not in again.output and rrd2.read_bytes() == before
    # record refuses it before opening the camera and the sensor.
    again = runner.invoke(app, ["record", str(tmp_path / "rec2"), "--simulate",
                                "wall:1.2:4:48x64", "--rerun-save", str(rrd2)])
    assert again.exit_code == 2 and "--rerun-save" in again.output
    assert not (tmp_path / "rec2").exists() and rrd2.read_bytes() == before


def test_cli_replay_bag_can_view_without_writing_a_bag(tmp_path):
    write_input_bag(tmp_path / "bag", frames=2)
    rrd = tmp_path / "bag.rrd"
    result = runner.invoke(app, ["replay", "--bag", str(tmp_path / "bag"), "--preset",
                                 "deltar-lite", "--rerun-save", str(rrd)])
    assert result.exit_code == 0, result.output
    assert "replayed 2 frames" in result.output
    rows = read_rrd(rrd)
    assert len(rows["/world/camera/image/depth"]) == 2
    missing = runner.invoke(app, ["replay", "--bag", str(tmp_path / "bag"), "--preset",
                                  "deltar-lite"])
    assert missing.exit_code != 0 and "--out-bag BAG, --rerun or --rerun-save" in missing.output


def test_cli_replay_folder_views_and_writes(tmp_path):
    rec = tmp_path / "rec"
    assert runner.invoke(app, ["record", str(rec), "--simulate", "wall:1.5:6:48x64"]).exit_code == 0
    rrd = tmp_path / "replay.rrd"
    result = runner.invoke(app, ["replay", str(rec), "--preset", "deltar-lite", "--out",
                                 str(tmp_path / "out"), "--outputs", "npy",
                                 "--rerun-save", str(rrd)])
    assert result.exit_code == 0, result.output
    rows = read_rrd(rrd)
    saved = sorted((tmp_path / "out").glob("*_depth_m.npy"))
    assert len(saved) == 3 == len(rows["/world/camera/image/depth"])
    np.testing.assert_allclose(_buffer(rows["/world/camera/image/depth"][0], "DepthImage"),
                               np.load(saved[0]))
    only_view = runner.invoke(app, ["replay", str(rec), "--preset", "deltar-lite",
                                    "--rerun-save", str(tmp_path / "v.rrd")])
    assert only_view.exit_code == 0, only_view.output
    assert len(read_rrd(tmp_path / "v.rrd")["/world/camera/image/depth"]) == 3
    nothing = runner.invoke(app, ["replay", str(rec), "--preset", "deltar-lite"])
    assert nothing.exit_code != 0 and "give --out DIR" in nothing.output


@pytest.mark.parametrize("command", ["predict", "record", "replay", "map"])
def test_rerun_without_a_display_is_refused_before_the_work(tmp_path, monkeypatch, command):
    import deltar.cli.checks as checks
    import deltar.cli.robotics as robotics

    # A headless Linux machine with no viewer running, whatever the one running the
    # tests has.
    monkeypatch.setattr(checks.sys, "platform", "linux")
    monkeypatch.setattr(robotics, "RERUN_VIEWER_ADDRESS", ("127.0.0.1", 1))
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    missing = tmp_path / "missing"
    args = {"predict": ["predict", "--image", str(tmp_path / "image.png"), "--zones",
                        str(tmp_path / "zones.json"), "--out", str(tmp_path / "out")],
            "record": ["record", str(tmp_path / "rec"), "--simulate", "wall:1.2:2:48x64"],
            "replay": ["replay", str(missing)],
            "map": ["map", str(missing), "--out", str(tmp_path / "map")]}[command]
    result = runner.invoke(app, [*args, "--rerun"])
    assert result.exit_code == 2, result.output
    assert "the viewer needs a display" in result.output and "--rerun-save" in result.output
    assert not (tmp_path / "rec").exists() and not (tmp_path / "out").exists()


def test_rerun_without_a_display_connects_to_a_viewer_already_listening(monkeypatch):
    import socket

    import deltar.cli.checks as checks
    import deltar.cli.robotics as robotics

    monkeypatch.setattr(checks.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with socket.socket() as viewer:  # e.g. `rerun --web-viewer` on a headless machine
        viewer.bind(("127.0.0.1", 0))
        viewer.listen()
        monkeypatch.setattr(robotics, "RERUN_VIEWER_ADDRESS", viewer.getsockname())
        robotics.check_viewer(True, None)  # no refusal
    with pytest.raises(Exception, match="the viewer needs a display"):
        robotics.check_viewer(True, None)  # the viewer gone
