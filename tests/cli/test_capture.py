"""``deltar record --targets``: several targets per zone, with their signals, recorded."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.cli.main import app
from deltar.io.recording import Recording
from deltar.io.rosbag_reader import BagInput

runner = CliRunner(env={"COLUMNS": "200"})
SOURCE = "procedural:4:4:96x128"


def _frames(out, bag: bool):
    if bag:
        return [pair.zone_frame for pair in BagInput(out).pairs()]
    return Recording(out).zone_frames()


@pytest.mark.parametrize("bag", [False, True], ids=["folder", "bag"])
def test_record_simulate_with_targets_keeps_every_target_and_its_signal(tmp_path, bag):
    out, single = tmp_path / "targets", tmp_path / "single"
    extra = ["--bag"] if bag else []
    for folder, targets in ((out, ["--targets", "3"]), (single, [])):
        result = runner.invoke(app, ["record", str(folder), "--simulate", SOURCE,
                                     "--sensor-hz", "30", *targets, *extra])
        assert result.exit_code == 0, result.output
    frames, plain = _frames(out, bag), _frames(single, bag)
    assert len(frames) == len(plain) > 0
    seconds = 0
    for frame, one in zip(frames, plain, strict=True):
        assert one.target_mean_m is None and one.target_signal is None
        assert frame.targets_per_zone == 3
        np.testing.assert_array_equal(frame.valid, one.valid)
        np.testing.assert_allclose(frame.mean_m, one.mean_m, atol=1e-6)
        valid = frame.target_valid
        assert np.all(frame.target_signal[valid] > 0)
        assert np.all(frame.target_signal[~valid] == 0)
        seconds += int(valid[..., 1].sum())
    assert seconds > 0  # these procedural rooms have depth edges inside a few zones


def test_record_targets_out_of_range_is_refused(tmp_path):
    result = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate", "wall:1.5:2",
                                 "--targets", "5"])
    assert result.exit_code != 0 and "--targets" in result.output
    assert not (tmp_path / "rec").exists()


def _posed_folder(folder, frames=4):
    """A small RGB-D folder (color/, depth/, camera-intrinsics.txt) with pose/ files."""
    import cv2

    from deltar.io.pose_file import write_pose_file

    rng = np.random.default_rng(0)
    for sub in ("color", "depth", "pose"):
        (folder / sub).mkdir(parents=True)
    (folder / "camera-intrinsics.txt").write_text("60 0 31.5\n0 60 23.5\n0 0 1\n")
    for i in range(frames):
        cv2.imwrite(str(folder / "color" / f"{i:06d}.png"),
                    rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), np.full((48, 64), 1500, np.uint16))
        pose = np.eye(4)
        pose[:3, 3] = (0.05 * i, 0.0, 0.0)
        write_pose_file(folder / "pose" / f"{i:06d}.txt", pose)
    return folder


def test_record_simulate_carries_the_sources_poses_and_appends_after_its_end(tmp_path):
    from deltar.mapping.poses import read_bag_poses, read_pose_folder

    source, out = _posed_folder(tmp_path / "scene"), tmp_path / "rec"
    for run in (1, 2):  # the second run appends, its clock after the first's end
        result = runner.invoke(app, ["record", str(out), "--simulate", str(source)])
        assert result.exit_code == 0, result.output
        assert "4 camera poses" in result.output
        assert ("appended to the recording" in result.output) == (run == 2)
        # Appending replays the source from its start: said before it happens.
        assert ("plays " in result.output and "from its first frame again" in " ".join(
            result.output.split())) == (run == 2)
        assert len(Recording(out).color_paths) == 4 * run
    found = read_pose_folder(out / "pose")
    order = np.argsort([int(name) for name in found.names])
    np.testing.assert_allclose(found.poses[order, 0, 3], [0.0, 0.05, 0.1, 0.15] * 2)
    times = [frame.timestamp_s for frame in Recording(out).zone_frames()]
    assert len(times) == 4 and np.all(np.diff(times) > 0)
    bag = tmp_path / "bag"
    result = runner.invoke(app, ["record", str(bag), "--bag", "--simulate", str(source)])
    assert result.exit_code == 0, result.output
    from_bag = read_bag_poses(bag)  # deltar's own pose topic, no --pose-topic needed
    np.testing.assert_allclose(from_bag.poses[:, 0, 3], [0.0, 0.05, 0.1, 0.15], atol=1e-9)
    np.testing.assert_allclose(from_bag.times_s, np.arange(4) / 30.0, atol=1e-9)


def test_record_never_writes_into_its_own_source(tmp_path):
    source = _posed_folder(tmp_path / "scene", frames=2)
    before = sorted(p.relative_to(source) for p in source.rglob("*"))
    for out in (source, source / "rec"):
        result = runner.invoke(app, ["record", str(out), "--simulate", str(source)])
        assert result.exit_code == 1 and "error: OUT" in result.output
        assert str(source) in result.output
    assert sorted(p.relative_to(source) for p in source.rglob("*")) == before


def test_replay_resumes_with_skip_existing(tmp_path):
    out = tmp_path / "rec"
    assert runner.invoke(app, ["record", str(out), "--simulate", "wall:1.5:6:48x64"]
                         ).exit_code == 0
    args = ["replay", str(out), "--out", str(tmp_path / "o"), "--outputs", "npy,png16",
            "--preset", "deltar-lite", "--threads", "1"]
    assert runner.invoke(app, [*args, "--limit", "2"]).exit_code == 0
    first = sorted((tmp_path / "o").iterdir())
    stamps = {p: p.stat().st_mtime_ns for p in first}
    first[0].unlink()  # one frame with only some of its outputs
    again = runner.invoke(app, args)
    assert again.exit_code == 1 and "pass --overwrite to replace them or --skip-existing" \
        in again.output
    resumed = runner.invoke(app, [*args, "--skip-existing"])
    assert resumed.exit_code == 0, resumed.output
    assert len(list((tmp_path / "o").iterdir())) == 6  # three frames, two outputs each
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items() if p != first[0])
    assert first[0].exists()
    both = runner.invoke(app, [*args, "--skip-existing", "--overwrite"])
    assert both.exit_code == 2 and "--skip-existing" in both.output


def test_record_simulate_refuses_hardware_options(tmp_path):
    for extra, named in ((["--calib", "calib.json"], "--calib is for hardware"),
                         (["--camera", "3", "--sensor", "sparkfun"],
                          "--camera and --sensor are for hardware")):
        result = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate",
                                     "wall:1.5:2:48x64", *extra])
        assert result.exit_code == 2 and named in result.output
    assert not (tmp_path / "rec").exists()


def test_replay_of_a_bag_refuses_the_folder_options(tmp_path):
    bag = tmp_path / "bag"
    assert runner.invoke(app, ["record", str(bag), "--bag", "--simulate", "wall:1.5:2:48x64"]
                         ).exit_code == 0
    for option in (["--keep-going"], ["--skip-existing"], ["--overwrite"],
                   ["--outputs", "npy"]):
        result = runner.invoke(app, ["replay", "--bag", str(bag), "--out-bag",
                                     str(tmp_path / "out"), *option])
        assert result.exit_code == 2 and f"{option[0]} is for replays into an --out folder" \
            in result.output
    assert not (tmp_path / "out").exists()


def test_replay_with_both_out_and_show_says_not_both(tmp_path):
    result = runner.invoke(app, ["replay", str(tmp_path / "rec"), "--out", str(tmp_path / "o"),
                                 "--show"])
    assert result.exit_code == 2
    assert "give --out DIR or --show, not both" in result.output
    neither = runner.invoke(app, ["replay", str(tmp_path / "rec")])
    assert neither.exit_code == 2 and "give --out DIR, or --show" in neither.output
    assert not (tmp_path / "o").exists()


def test_record_refuses_a_folder_of_other_files_and_a_viewer_file_inside_before_work(tmp_path):
    data_set = tmp_path / "rgbd"
    data_set.mkdir()
    (data_set / "000000.png").write_bytes(b"a frame of someone's data set")
    result = runner.invoke(app, ["record", str(data_set), "--simulate", "wall:1.2:2:48x64",
                                 "--rerun-save", str(tmp_path / "view.rrd")])
    assert result.exit_code == 1
    assert "rgbd is not empty and holds no recording (no meta.json)" in result.output
    assert sorted(p.name for p in data_set.iterdir()) == ["000000.png"]
    assert not (tmp_path / "view.rrd").exists()
    inside = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate",
                                 "wall:1.2:2:48x64", "--rerun-save",
                                 str(tmp_path / "rec" / "view.rrd")])
    assert inside.exit_code == 2 and "is inside the recording" in inside.output
    assert not (tmp_path / "rec").exists()


def test_replay_without_calib_warns_unless_the_recording_is_simulated(tmp_path):
    import json

    recorded = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate",
                                   "wall:1.2:2:48x64"])
    assert recorded.exit_code == 0, recorded.output
    lite = ["--preset", "deltar-lite", "--threads", "1", "--outputs", "npy"]
    simulated = runner.invoke(app, ["replay", str(tmp_path / "rec"), "--out",
                                    str(tmp_path / "a"), *lite])
    assert simulated.exit_code == 0 and "no --calib" not in simulated.output
    meta = tmp_path / "rec" / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "sensor_model": "VL53L5CX"}))
    real = runner.invoke(app, ["replay", str(tmp_path / "rec"), "--out", str(tmp_path / "b"),
                               *lite])
    assert real.exit_code == 0, real.output
    assert "warning: no --calib: the zones are placed with" in real.output
    # The calibration rigs' recordings simulate a sensor beside the camera: they warn too.
    from deltar.calibration.board import parse_board_spec
    from deltar.calibration.synthetic import SYNTHETIC_RIG_SENSOR
    from deltar.calibration.synthetic_board import board_view_poses, write_board_recording
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    write_board_recording(tmp_path / "board", SensorExtrinsics(translation_m=[0.05, 0, 0]),
                          CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48),
                          parse_board_spec("charuco:5x4:0.06:0.045:DICT_4X4_50"),
                          board_view_poses(2, distance_m=(0.6, 0.6), seed=1))
    assert Recording(tmp_path / "board").meta.sensor_model == SYNTHETIC_RIG_SENSOR
    rig = runner.invoke(app, ["replay", str(tmp_path / "board"), "--out", str(tmp_path / "c"),
                              *lite])
    assert "warning: no --calib" in rig.output


def test_replay_writes_each_image_once_when_zone_frames_share_it(tmp_path):
    from deltar.cli.capture import _check_replay
    from tests.capture.test_replay import double_zone_frames

    rec, out = tmp_path / "rec", tmp_path / "o"
    assert runner.invoke(app, ["record", str(rec), "--simulate", "wall:1.5:6:48x64"]
                         ).exit_code == 0
    double_zone_frames(rec)  # two zone frames nearest each paired image
    images = len({p.color_path for p in Recording(rec).pairs()})
    assert _check_replay(rec, out, ("npy",), (0.02, 0.0), 1, None, False, False) == images
    args = ["replay", str(rec), "--out", str(out), "--outputs", "npy", "--preset",
            "deltar-lite", "--threads", "1"]
    with pytest.warns(UserWarning, match="share a colour image with a zone frame nearer"):
        result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert f"wrote {images} files" in result.output
    assert len(list(out.iterdir())) == images


def test_replay_of_a_bag_checks_calib_before_the_model_and_applies_its_options(
        tmp_path, monkeypatch):
    from deltar.calibration.rig import RigCalibration
    from deltar.cli.model_options import ModelOptions
    from deltar.sensor.geometry import SensorExtrinsics
    from tests.capture.test_bag_replay import INTR, MS, _bag

    _bag(tmp_path / "bag", [4 * MS, 104 * MS, 204 * MS], invalid=(1,))
    args = ["replay", "--bag", str(tmp_path / "bag"), "--preset", "deltar-lite",
            "--threads", "1"]
    for grid, size, named in ((4, INTR, "--calib is for a 4x4 zone grid, the bag"),
                              (8, INTR.scaled(96, 128), "the images of /camera/image is 48x64 "
                               "pixels but --calib is for the calibrated resolution 96x128")):
        calib = RigCalibration(size, SensorExtrinsics(), grid=grid).save(
            tmp_path / f"calib{grid}.json")
        with monkeypatch.context() as patch:
            patch.setattr(ModelOptions, "load", lambda self: pytest.fail("model loaded"))
            result = runner.invoke(app, [*args, "--out-bag", str(tmp_path / "o"),
                                         "--calib", str(calib)])
        assert result.exit_code == 1 and named in result.output, result.output
    with pytest.warns(UserWarning, match="has no valid zone; skipped"):
        result = runner.invoke(app, [*args, "--out-bag", str(tmp_path / "skip")])
    assert result.exit_code == 0 and "wrote 2 frames" in result.output, result.output
    with pytest.warns(UserWarning, match="has no valid zone; image-only estimate"):
        result = runner.invoke(app, [*args, "--out-bag", str(tmp_path / "all"),
                                     "--allow-no-zones"])
    assert result.exit_code == 0 and "wrote 3 frames" in result.output, result.output
    # Stamps 4 ms after each image, shifted 30 ms more: 34 ms from every image.
    result = runner.invoke(app, [*args, "--out-bag", str(tmp_path / "late"),
                                 "--time-offset", "0.03", "--allow-no-zones"])
    assert result.exit_code == 1 and "no ToF message on /tof/zones has a camera image" \
        in result.output, result.output
