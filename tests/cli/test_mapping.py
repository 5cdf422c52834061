"""``deltar map`` end to end on a tiny recording, and every bad input's one error line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from deltar.cli.main import app
from deltar.mapping.poses import write_tum_trajectory
from tests.mapping.conftest import (
    SMALL,
    WALL_Z_M,
    pose_at,
    render_wall,
    write_wall_recording,
)

runner = CliRunner()
COARSE = ["--voxel", "0.04", "--truncation", "3"]


@pytest.fixture
def wall_recording(tmp_path):
    return write_wall_recording(tmp_path / "rec")


def _run(*args):
    return runner.invoke(app, ["map", *[str(a) for a in args]])


def _error(result, *needles):
    assert result.exit_code != 0, result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert "mapping:" not in result.stdout  # failed before the long part
    return lines[0]


def _read_mesh(path):
    from deltar.mapping.tsdf import require_open3d

    return require_open3d().io.read_triangle_mesh(str(path))


def test_map_of_the_recorded_depth_with_the_recordings_poses(wall_recording, tmp_path):
    out = tmp_path / "map"
    result = _run(wall_recording, "--out", out, "--method", "recorded", *COARSE)
    assert result.exit_code == 0, result.output
    assert "recorded poses" in result.stdout and "volume:" in result.stdout
    assert "MiB used" in result.stdout
    vertices = np.asarray(_read_mesh(out / "mesh.ply").vertices)
    assert np.abs(vertices[:, 2] - WALL_Z_M).max() < 0.02
    summary = json.loads((out / "map.json").read_text())
    assert summary["frames"] == 6 and summary["max_depth_m"] == 4.0
    assert summary["memory_bytes"] >= summary["used_bytes"] > 0
    trajectory = np.loadtxt(out / "trajectory.txt")
    assert trajectory.shape == (6, 8)
    np.testing.assert_allclose(trajectory[:, 1], 0.05 * np.arange(6), atol=1e-6)
    again = _run(wall_recording, "--out", out, "--method", "recorded", *COARSE)
    _error(again, "exist")
    (out / "map.json").unlink()  # a map stopped while its outputs were being written
    again = _run(wall_recording, "--out", out, "--method", "recorded", *COARSE)
    _error(again, "holds an unfinished map (mesh.ply, points.ply, trajectory.txt, no "
           "map.json: it was stopped while being written); pass --overwrite")


def test_map_with_the_bundled_model_and_a_baseline(wall_recording, tmp_path):
    result = _run(wall_recording, "--out", tmp_path / "model", *COARSE, "--threads", "1")
    assert result.exit_code == 0, result.output
    mesh = _read_mesh(tmp_path / "model" / "mesh.ply")
    assert len(mesh.triangles) > 0
    # The zones say 2 m; the model's wall is near it (tolerance: a model, not a ruler).
    assert np.median(np.asarray(mesh.vertices)[:, 2]) == pytest.approx(WALL_Z_M, abs=0.3)
    assert json.loads((tmp_path / "model" / "map.json").read_text())["beyond_grid"] is False
    result = _run(wall_recording, "--out", tmp_path / "bilinear", "--method", "bilinear",
                  *COARSE)
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "bilinear" / "map.json").read_text())["depth"] == "bilinear"


def test_a_tum_trajectory_gives_the_poses(wall_recording, tmp_path):
    shutil.rmtree(wall_recording / "pose")
    times = 0.05 * np.arange(-1, 8)  # recording frames are at i / 30 s
    path = write_tum_trajectory(tmp_path / "t.txt", times,
                                np.stack([pose_at(1.5 * t) for t in times]))
    result = _run(wall_recording, "--out", tmp_path / "map", "--method", "recorded",
                  "--trajectory", path, *COARSE)
    assert result.exit_code == 0, result.output
    trajectory = np.loadtxt(tmp_path / "map" / "trajectory.txt")
    np.testing.assert_allclose(trajectory[:, 1], 1.5 * trajectory[:, 0], atol=1e-6)


def test_no_output_replaces_an_input_file_in_the_output_folder(wall_recording, tmp_path):
    """A --trajectory, --calib or checkpoint kept in --out under an output's name is
    refused before any work, whatever --overwrite says."""
    shutil.rmtree(wall_recording / "pose")
    out = tmp_path / "map"
    out.mkdir()
    times = 0.05 * np.arange(-1, 8)
    trajectory = write_tum_trajectory(out / "trajectory.txt", times,
                                      np.stack([pose_at(1.5 * t) for t in times]))
    content = trajectory.read_bytes()
    _error(_run(wall_recording, "--out", out, "--method", "recorded", "--trajectory",
                trajectory, "--overwrite"),
           f"--out {trajectory} is the input {trajectory}", "whatever --overwrite says")
    calibration = out / "map.json"
    calibration.write_text("{}")
    _error(_run(wall_recording, "--out", out, "--calib", calibration, "--overwrite"),
           f"--out {calibration} is the input {calibration}")
    checkpoint = out / "mesh.ply"
    checkpoint.write_bytes(b"weights")
    _error(_run(wall_recording, "--out", out, "--checkpoint", checkpoint, "--overwrite"),
           f"--out {checkpoint} is the input {checkpoint}")
    assert trajectory.read_bytes() == content and calibration.read_text() == "{}"
    assert checkpoint.read_bytes() == b"weights"


def test_odometry_without_poses_writes_the_map_and_reports_its_error(wall_recording,
                                                                     tmp_path):
    result = _run(wall_recording, "--out", tmp_path / "map", "--method", "recorded",
                  "--odometry", *COARSE)
    assert result.exit_code == 0, result.output
    assert "odometry: 5 frame pairs" in result.stdout and "ATE" in result.stdout
    assert "m/s" not in result.stderr  # a plausible walk: no warning
    summary = json.loads((tmp_path / "map" / "map.json").read_text())
    assert summary["ate_m"] < 0.05  # exact depth, strong texture: it tracks
    assert (tmp_path / "map" / "mesh.ply").is_file()


# ---------------------------------------------------------------------- bad input
def test_poses_that_are_not_rotations(wall_recording, tmp_path):
    first = sorted((wall_recording / "pose").iterdir())[0]
    first.write_text("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n")
    _error(_run(wall_recording, "--out", tmp_path / "m", "--method", "recorded"),
           first.name, "is not a rotation")


def test_a_trajectory_that_covers_none_of_the_frames(wall_recording, tmp_path):
    shutil.rmtree(wall_recording / "pose")
    path = write_tum_trajectory(tmp_path / "t.txt", np.array([50.0, 51.0]),
                                np.stack([pose_at(0), pose_at(1)]))
    _error(_run(wall_recording, "--out", tmp_path / "m", "--method", "recorded",
                "--trajectory", path), "covers none of the frames", "same clock")


def test_trajectory_beside_the_recordings_own_poses(wall_recording, tmp_path):
    path = write_tum_trajectory(tmp_path / "t.txt", np.array([0.0]), pose_at(0)[None])
    _error(_run(wall_recording, "--out", tmp_path / "m", "--trajectory", path),
           "has its own poses", "give only one")


def test_too_short_for_odometry(tmp_path):
    from deltar.mapping.scenes import write_posed_recording

    rec = write_posed_recording(tmp_path / "rec", [(*render_wall(pose_at(0.05 * i)),
                                                    pose_at(0.05 * i)) for i in range(2)], SMALL)
    shutil.rmtree(rec / "pose")
    _error(_run(rec, "--out", tmp_path / "m", "--method", "recorded"),
           "2 frame(s) is too short for odometry")


def test_too_still_for_odometry(tmp_path):
    from deltar.mapping.scenes import write_posed_recording

    still = pose_at(0.0)
    rec = write_posed_recording(tmp_path / "rec", [(*render_wall(still), still)] * 4, SMALL)
    shutil.rmtree(rec / "pose")
    _error(_run(rec, "--out", tmp_path / "m", "--method", "recorded"),
           "too still for odometry", "median image change 0.00")


def test_a_volume_that_would_exceed_the_memory_budget(wall_recording, tmp_path):
    _error(_run(wall_recording, "--out", tmp_path / "m", "--method", "recorded",
                "--voxel", "0.005", "--max-memory", "2"),
           "one frame's view alone needs up to", "more than --max-memory 2 MiB")


def test_usage_errors(wall_recording, tmp_path):
    result = _run(wall_recording, "--out", tmp_path / "m", "--method", "nope")
    _error(result, "--method must be one of", "colorization", "recorded")
    result = _run(wall_recording, "--out", tmp_path / "m", "--method", "bilinear",
                  "--preset", "deltar-lite")
    assert result.exit_code == 2 and "not both" in result.output
    result = _run(wall_recording, "--out", tmp_path / "m", "--blend", "--network-only")
    assert result.exit_code == 2 and "not both" in result.output
    result = _run(wall_recording, "--out", tmp_path / "m", "--method", "bilinear",
                  "--beyond-grid")
    assert result.exit_code == 2 and "--beyond-grid" in result.output
    result = _run(wall_recording, "--out", wall_recording / "inside", "--method", "recorded")
    _error(result, "is inside the input")
    result = _run(tmp_path / "missing", "--out", tmp_path / "m", "--method", "recorded")
    _error(result, "not found")
    result = _run(wall_recording, "--out", tmp_path / "m", "--voxel", "-1")
    assert result.exit_code == 2 and "--voxel" in result.output


def _wall_bag(path, *, depth: bool):
    """A bag as ``deltar record --bag`` writes it: the wall seen from four poses, with its
    /camera/pose topic, and the reference depth when ``depth``."""
    from deltar.io.recording import RecordingMeta
    from deltar.io.rosbag_writer import BagRecordingWriter
    from deltar.sensor.geometry import zone_rects
    from deltar.sensor.simulate import simulate_zone_frame
    from deltar.sensor.zone_frame import ZoneFrame

    writer = BagRecordingWriter(path, RecordingMeta(SMALL))
    rects = zone_rects(SMALL, 8)
    for i in range(4):
        pose, t = pose_at(0.05 * i), 1.0 + i / 30
        image, wall_depth = render_wall(pose)
        writer.add_color(t, image)
        if depth:
            writer.add_depth(t, wall_depth)
        zones = simulate_zone_frame(wall_depth, rects)
        writer.add_zone_frame(ZoneFrame(zones.mean_m, zones.sigma_m, zones.valid,
                                        timestamp_s=t + 0.001, no_target=zones.no_target))
        writer.add_pose(t, pose)
    writer.close()
    return path


def test_map_of_a_ros2_bag_with_a_pose_topic(tmp_path):
    pytest.importorskip("rosbags")
    bag = _wall_bag(tmp_path / "bag", depth=False)
    result = _run(bag, "--out", tmp_path / "map", "--method", "bilinear",
                  "--pose-topic", "/camera/pose", *COARSE)
    assert result.exit_code == 0, result.output
    assert "/camera/pose" in result.stdout
    trajectory = np.loadtxt(tmp_path / "map" / "trajectory.txt")
    np.testing.assert_allclose(trajectory[:, 1], 0.05 * np.arange(4), atol=1e-6)
    vertices = np.asarray(_read_mesh(tmp_path / "map" / "mesh.ply").vertices)
    assert np.median(vertices[:, 2]) == pytest.approx(WALL_Z_M, abs=0.1)
    # Without a depth topic --method recorded is refused before any pose.
    refused = _run(bag, "--out", tmp_path / "map2", "--method", "recorded", *COARSE)
    _error(refused, "--method", "no recorded depth", "--depth-topic", "/camera/color/image_raw")
    assert "poses:" not in refused.output and not (tmp_path / "map2").exists()
    wrong = _run(bag, "--out", tmp_path / "map2", "--method", "recorded", "--depth-topic",
                 "/tof/zones", *COARSE)
    _error(wrong, "/tof/zones", "expected sensor_msgs/msg/Image", "--depth-topic")


def test_map_of_a_ros2_bags_recorded_depth_matches_the_recordings(tmp_path, wall_recording):
    pytest.importorskip("rosbags")
    bag = _wall_bag(tmp_path / "bag", depth=True)
    result = _run(bag, "--out", tmp_path / "map", "--method", "recorded", *COARSE)
    assert result.exit_code == 0, result.output
    assert "/camera/pose" in result.stdout  # deltar record's pose topic, found by itself
    vertices = np.asarray(_read_mesh(tmp_path / "map" / "mesh.ply").vertices)
    assert len(vertices) > 100
    assert np.median(vertices[:, 2]) == pytest.approx(WALL_Z_M, abs=0.02)
    assert _run(wall_recording, "--out", tmp_path / "map", "--method", "recorded",
                "--depth-topic", "/camera/depth/image").exit_code != 0
    only_recorded = _run(bag, "--out", tmp_path / "m3", "--method", "bilinear",
                         "--depth-topic", "/camera/depth/image", *COARSE)
    _error(only_recorded, "--depth-topic names the depth --method recorded maps")


def test_a_bags_depth_is_read_only_for_method_recorded(tmp_path):
    pytest.importorskip("rosbags")
    from deltar.io.recording import RecordingMeta
    from deltar.io.rosbag_writer import BagRecordingWriter
    from deltar.sensor.geometry import zone_rects
    from deltar.sensor.simulate import simulate_zone_frame
    from deltar.sensor.zone_frame import ZoneFrame

    # A depth topic of another size than the camera (not registered to it), and depth
    # only from the third frame on.
    writer = BagRecordingWriter(tmp_path / "bag", RecordingMeta(SMALL))
    for i in range(4):
        pose, t = pose_at(0.05 * i), 1.0 + i / 30
        image, depth = render_wall(pose)
        writer.add_color(t, image)
        if i >= 2:
            writer.writer.add_metric_image("/camera/depth/image", round(t * 1e9), "cam",
                                           depth[::2, ::2])
        zones = simulate_zone_frame(depth, zone_rects(SMALL, 8))
        writer.add_zone_frame(ZoneFrame(zones.mean_m, zones.sigma_m, zones.valid,
                                        timestamp_s=t + 0.001, no_target=zones.no_target))
        writer.add_pose(t, pose)
    writer.close()
    # Other methods never read it.
    result = _run(tmp_path / "bag", "--out", tmp_path / "map", "--method", "bilinear",
                  *COARSE)
    assert result.exit_code == 0, result.output
    # --method recorded refuses the frames without depth before any pose.
    refused = _run(tmp_path / "bag", "--out", tmp_path / "m2", "--method", "recorded",
                   *COARSE)
    _error(refused, "2 of 4 frames", "no recorded depth", "--tolerance")
    assert "poses:" not in refused.output


def test_rerun_save_writes_the_growing_map(wall_recording, tmp_path):
    pytest.importorskip("rerun")
    view = tmp_path / "map.rrd"
    result = _run(wall_recording, "--out", tmp_path / "map", "--method", "recorded",
                  "--rerun-save", view, *COARSE)
    assert result.exit_code == 0, result.output
    assert view.is_file() and view.stat().st_size > 10_000


def test_a_calibration_with_lens_distortion_runs_on_undistorted_frames(wall_recording,
                                                                        tmp_path):
    from deltar.calibration.rig import RigCalibration
    from deltar.sensor.geometry import SensorExtrinsics

    calib = RigCalibration(intrinsics=SMALL, extrinsics=SensorExtrinsics(), grid=8,
                           distortion=(0.05, 0.0, 0.0, 0.0))
    calib.save(tmp_path / "calib.json")
    result = _run(wall_recording, "--out", tmp_path / "map", "--method", "bilinear",
                  "--calib", tmp_path / "calib.json", *COARSE)
    assert result.exit_code == 0, result.output
    vertices = np.asarray(_read_mesh(tmp_path / "map" / "mesh.ply").vertices)
    # A smoke test: undistorting a pinhole render bends the wall a little, not far.
    assert np.median(vertices[:, 2]) == pytest.approx(WALL_Z_M, abs=0.1)


def test_a_calibration_of_another_grid_and_depth_of_another_size_are_refused_first(
        wall_recording, tmp_path):
    """Both named, before the poses line and the model: --calib for a 4x4 grid on an 8x8
    recording; a recorded depth image of another size than its colour image."""
    import cv2

    from deltar.calibration.rig import RigCalibration
    from deltar.sensor.geometry import SensorExtrinsics

    RigCalibration(intrinsics=SMALL, extrinsics=SensorExtrinsics(), grid=4).save(
        tmp_path / "calib4.json")
    _error(_run(wall_recording, "--out", tmp_path / "m", "--calib", tmp_path / "calib4.json"),
           "--calib is for a 4x4 zone grid", f"the recording {wall_recording} has 8x8")
    depth_file = sorted((wall_recording / "depth").iterdir())[0]
    depth = cv2.imread(str(depth_file), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(depth_file), cv2.resize(depth, None, fx=0.5, fy=0.5,
                                            interpolation=cv2.INTER_NEAREST))
    line = _error(_run(wall_recording, "--out", tmp_path / "m", "--method", "recorded"),
                  str(depth_file), "must be registered to the colour camera")
    assert "poses:" not in line


def test_poses_far_beyond_the_volume_are_refused_and_millimetres_warned(wall_recording,
                                                                      tmp_path):
    """Block indices would wrap for positions 1e12 m away (a garbage map); a trajectory in
    millimetres moves the camera at 1500 m/s, which is warned of."""
    shutil.rmtree(wall_recording / "pose")
    times = 0.05 * np.arange(-1, 8)
    poses = np.stack([pose_at(1.5 * t) for t in times])
    poses[::2, 0, 3] = 1e12
    far = write_tum_trajectory(tmp_path / "far.txt", times, poses)
    _error(_run(wall_recording, "--out", tmp_path / "m", "--method", "recorded",
                "--trajectory", far, *COARSE),
           f"{far} (TUM trajectory): camera positions lie up to 6.67e+11 m from the world "
           "origin", "are the poses in metres?")  # 2/3 of 1e12 m, interpolated
    poses = np.stack([pose_at(1.5 * t) for t in times])
    poses[:, :3, 3] *= 1000
    millimetres = write_tum_trajectory(tmp_path / "mm.txt", times, poses)
    with pytest.warns(UserWarning, match=r"the camera moves 1\.5e\+03 m/s between frames "
                      r"\(median\); are the poses' translations in metres"):
        result = _run(wall_recording, "--out", tmp_path / "mm", "--method", "recorded",
                      "--trajectory", millimetres, *COARSE)
    assert result.exit_code == 0, result.output


def test_a_memory_budget_above_open3ds_limit_is_clipped_with_a_warning(wall_recording,
                                                                       tmp_path):
    from deltar.mapping.tsdf import MAX_BLOCKS

    result = _run(wall_recording, "--out", tmp_path / "m", "--method", "recorded",
                  "--max-memory", "8192", *COARSE)
    assert result.exit_code == 0, result.output
    assert f"--max-memory 8192 MiB is clipped to {MAX_BLOCKS} blocks" in result.stderr
    assert f"at most {MAX_BLOCKS} blocks" in result.stdout


def test_a_voxel_or_truncation_as_deep_as_the_depth_limit_is_refused_first(wall_recording,
                                                                         tmp_path):
    for options in (["--voxel", "2"], ["--max-depth", "0.05"]):
        line = _error(_run(wall_recording, "--out", tmp_path / "m", "--method", "recorded",
                           *options), "--truncation x --voxel", "--max-depth",
                      "at most a quarter")
        assert "poses:" not in line
        assert not (tmp_path / "m").exists()


def test_options_that_would_be_ignored_are_refused(wall_recording, tmp_path):
    """Model options have no effect on a --method's depth, bag options none on a
    recording folder: each is refused by name rather than dropped."""
    for options in (["--flip"], ["--size", "64x96"], ["--network-only"], ["--blend"],
                    ["--max-relative-sigma", "0.2"], ["--threads", "1"]):
        result = _run(wall_recording, "--out", tmp_path / "m", "--method", "bilinear",
                      *options)
        assert result.exit_code == 2, (options, result.output)
        assert f"{options[0]} is a model option" in result.output
    for options in (["--image-topic", "/camera/image"], ["--tof-sigma", "0.01"],
                    ["--pose-topic", "/camera/pose"]):
        result = _run(wall_recording, "--out", tmp_path / "m", "--method", "bilinear",
                      *options)
        assert result.exit_code == 2, (options, result.output)
        assert f"{options[0]} is for ROS 2 bags" in result.output
    assert not (tmp_path / "m").exists()


def test_a_bags_pose_topic_and_a_trajectory_are_not_both_taken(tmp_path):
    pytest.importorskip("rosbags")
    bag = _wall_bag(tmp_path / "bag", depth=False)
    trajectory = write_tum_trajectory(tmp_path / "t.txt", 1.0 + np.arange(4) / 30,
                                      np.stack([pose_at(0.05 * i) for i in range(4)]))
    _error(_run(bag, "--out", tmp_path / "m", "--method", "bilinear", "--pose-topic",
                "/camera/pose", "--trajectory", trajectory, *COARSE),
           "--trajectory", "--pose-topic /camera/pose", "give only one")


def test_rerun_save_is_checked_like_the_outputs_before_the_run(wall_recording, tmp_path):
    out = tmp_path / "map"
    _error(_run(wall_recording, "--out", out, "--method", "recorded", "--rerun-save",
                out / "mesh.ply", *COARSE), "--rerun-save", "is one of the map's outputs")
    _error(_run(wall_recording, "--out", out, "--method", "recorded", "--rerun-save",
                wall_recording / "view.rrd", *COARSE), "--rerun-save", "is inside the input")
    (tmp_path / "old.rrd").write_bytes(b"x")
    result = _run(wall_recording, "--out", out, "--method", "recorded", "--rerun-save",
                  tmp_path / "old.rrd", *COARSE)
    assert result.exit_code == 2 and "exists" in result.output
    assert not out.exists() and not (wall_recording / "view.rrd").exists()
