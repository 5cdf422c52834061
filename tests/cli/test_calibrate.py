"""``deltar calibrate`` end to end on a small synthetic recording."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from deltar.calibration.rig import RigCalibration
from deltar.calibration.slam import write_ply_points
from deltar.calibration.synthetic import synthetic_rig_frames, write_synthetic_recording
from deltar.camera import CameraIntrinsics
from deltar.cli.main import app
from deltar.sensor.geometry import SensorExtrinsics

CAMERA = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [92.0, -1.0, 1.5], degrees=True).as_matrix(),
                        np.array([0.03, 0.01, -0.01]))


def test_calibrate_writes_calibration_report_and_pictures(tmp_path):
    frames = synthetic_rig_frames(TRUE, CAMERA, frames_per_plane=3, mean_noise_m=0.015, seed=5)
    write_synthetic_recording(tmp_path / "rec", frames, CAMERA)
    out = tmp_path / "calib.json"
    args = ["calibrate", str(tmp_path / "rec"), "--out", str(out), "--nominal-roll-deg", "90",
            "--plot", str(tmp_path / "plots")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "cm before" in result.output and "frames used: 18" in result.output
    calib = RigCalibration.load(out)
    error = Rotation.from_matrix(calib.extrinsics.rotation @ TRUE.rotation.T).magnitude()
    assert np.degrees(error) < 0.5
    assert np.linalg.norm(calib.extrinsics.translation_m - TRUE.translation_m) < 0.01
    residuals = calib.residuals
    assert residuals["zone_to_cloud_after_m"] < residuals["zone_to_cloud_before_m"]
    pictures = sorted((tmp_path / "plots").glob("zones_*.png"))
    assert len(pictures) == 3 and all(p.stat().st_size > 1000 for p in pictures)
    # The output is never silently replaced.
    again = CliRunner().invoke(app, args)
    assert again.exit_code != 0 and "exists" in again.output


def test_calibrate_reports_degenerate_recordings(tmp_path):
    frames = synthetic_rig_frames(TRUE, CAMERA, view_planes=(2,), frames_per_plane=4,
                                  tilt_deg=1.0, mean_noise_m=0.0, seed=6)
    write_synthetic_recording(tmp_path / "rec", frames, CAMERA)
    result = CliRunner().invoke(app, ["calibrate", str(tmp_path / "rec"), "--out",
                                      str(tmp_path / "c.json")])
    assert result.exit_code == 1
    assert "all planes are parallel" in result.output
    assert not (tmp_path / "c.json").exists()


def test_calibrate_missing_recording(tmp_path):
    result = CliRunner().invoke(app, ["calibrate", str(tmp_path / "nope"), "--out",
                                      str(tmp_path / "c.json")])
    assert result.exit_code == 1 and "not found" in result.output


def test_calibrate_from_a_slam_map(tmp_path):
    frames = synthetic_rig_frames(TRUE, CAMERA, frames_per_plane=3, mean_noise_m=0.015, seed=7)
    write_synthetic_recording(tmp_path / "rec", frames, CAMERA, with_depth=False)
    # The map: points on the room's six faces (5 cm grid); the trajectory: the camera poses.
    half = np.array([2.5, 1.3, 3.0])
    faces = []
    for axis in range(3):
        a, b = (i for i in range(3) if i != axis)
        ga, gb = np.meshgrid(np.arange(-half[a], half[a], 0.05),
                             np.arange(-half[b], half[b], 0.05))
        for sign in (-1, 1):
            face = np.zeros((ga.size, 3))
            face[:, a], face[:, b], face[:, axis] = ga.ravel(), gb.ravel(), sign * half[axis]
            faces.append(face)
    write_ply_points(tmp_path / "map.ply", np.concatenate(faces), binary=False)
    lines = [" ".join(f"{v:.9f}" for v in (f.zone_frame.timestamp_s, *f.cam_to_world[:3, 3],
                                             *Rotation.from_matrix(f.cam_to_world[:3, :3])
                                             .as_quat())) for f in frames]
    (tmp_path / "traj.txt").write_text("# t tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    result = CliRunner().invoke(app, [
        "calibrate", str(tmp_path / "rec"), "--out", str(tmp_path / "c.json"),
        "--slam-cloud", str(tmp_path / "map.ply"), "--slam-trajectory",
        str(tmp_path / "traj.txt")])
    assert result.exit_code == 0, result.output
    calib = RigCalibration.load(tmp_path / "c.json")
    error = Rotation.from_matrix(calib.extrinsics.rotation @ TRUE.rotation.T).magnitude()
    assert np.degrees(error) < 0.5
    assert np.linalg.norm(calib.extrinsics.translation_m - TRUE.translation_m) < 0.01
    half_given = CliRunner().invoke(app, ["calibrate", str(tmp_path / "rec"), "--out",
                                          str(tmp_path / "d.json"), "--slam-cloud",
                                          str(tmp_path / "map.ply")])
    assert half_given.exit_code != 0


def test_calibrate_refuses_plot_folder_equal_to_out(tmp_path):
    # Found before calibrating: not after writing --out, as a "File exists" error.
    frames = synthetic_rig_frames(TRUE, CAMERA, frames_per_plane=2, mean_noise_m=0.01, seed=5)
    write_synthetic_recording(tmp_path / "rec", frames, CAMERA)
    out = tmp_path / "same"
    result = CliRunner().invoke(app, ["calibrate", str(tmp_path / "rec"), "--out", str(out),
                                      "--plot", str(out)])
    assert result.exit_code == 2
    assert "--plot" in result.output and "also --out" in result.output
    assert not out.exists()
