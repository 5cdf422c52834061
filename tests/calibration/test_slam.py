"""SLAM inputs: PLY and TUM readers, pose interpolation, calibration from a SLAM map."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.extrinsic import nominal_extrinsics
from deltar.calibration.pipeline import calibrate_recording
from deltar.calibration.slam import (
    Trajectory,
    read_ply_points,
    read_tum_trajectory,
    write_ply_points,
)
from deltar.calibration.synthetic import synthetic_rig_frames, write_synthetic_recording
from deltar.camera import CameraIntrinsics
from deltar.io.recording import Recording
from deltar.sensor.geometry import SensorExtrinsics

POINTS = np.array([[0.5, -1.25, 2.0], [1.0, 2.0, 3.0], [-4.5, 0.0, 0.125]])


def _header(fmt: str, extra: str = "") -> str:
    return (f"ply\nformat {fmt} 1.0\ncomment made by hand\nelement vertex 3\n"
            "property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
            f"element face 1\nproperty list uchar int vertex_indices\n{extra}end_header\n")


def test_ascii_ply_with_extra_properties_and_faces(tmp_path):
    body = "".join(f"{x} {y} {z} 200\n" for x, y, z in POINTS) + "3 0 1 2\n"
    (tmp_path / "a.ply").write_text(_header("ascii") + body)
    np.testing.assert_allclose(read_ply_points(tmp_path / "a.ply"), POINTS)


def test_binary_little_endian_ply(tmp_path):
    record = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    table = np.zeros(3, record)
    table["x"], table["y"], table["z"], table["red"] = *POINTS.T, 7
    face = np.array([3], "u1").tobytes() + np.array([0, 1, 2], "<i4").tobytes()
    data = _header("binary_little_endian").encode() + table.tobytes() + face
    (tmp_path / "b.ply").write_bytes(data)
    np.testing.assert_allclose(read_ply_points(tmp_path / "b.ply"), POINTS)
    # Our own writer reads back (float32 precision).
    write_ply_points(tmp_path / "c.ply", POINTS)
    np.testing.assert_allclose(read_ply_points(tmp_path / "c.ply"), POINTS, atol=1e-6)


def test_bad_ply_files(tmp_path):
    (tmp_path / "x.ply").write_text("hello")
    with pytest.raises(ValueError, match="not a PLY"):
        read_ply_points(tmp_path / "x.ply")
    (tmp_path / "big.ply").write_text(_header("binary_big_endian"))
    with pytest.raises(ValueError, match="unsupported PLY format"):
        read_ply_points(tmp_path / "big.ply")
    (tmp_path / "short.ply").write_bytes(_header("binary_little_endian").encode() + b"\0" * 10)
    with pytest.raises(ValueError, match="truncated"):
        read_ply_points(tmp_path / "short.ply")
    with pytest.raises(FileNotFoundError):
        read_ply_points(tmp_path / "none.ply")
    for bad in ("nan", "inf"):
        body = "".join(f"{x} {y} {z} 200\n" for x, y, z in POINTS).replace(
            f"{POINTS[1][0]} ", f"{bad} ", 1) + "3 0 1 2\n"
        (tmp_path / "damaged.ply").write_text(_header("ascii") + body)
        with pytest.raises(ValueError, match=r"damaged\.ply: 1 of 3 vertices are NaN or "
                           r"infinite \(the first at index 1\)"):
            read_ply_points(tmp_path / "damaged.ply")


def test_tum_trajectory_quaternion_order_and_interpolation(tmp_path):
    s = np.sqrt(0.5)
    (tmp_path / "traj.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        "1.0 0 0 0 0 0 0 1\n"
        f"2.0 1 2 3 0 0 {s} {s}\n"   # 90 deg about z
        "5.0 1 2 3 0 0 0 1\n")
    traj = read_tum_trajectory(tmp_path / "traj.txt")
    np.testing.assert_allclose(traj.poses[1][:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(traj.poses[1][:3, 3], [1, 2, 3])
    mid = traj.pose_at(1.5, max_gap_s=1.0)
    np.testing.assert_allclose(mid[:3, 3], [0.5, 1.0, 1.5])
    angle = Rotation.from_matrix(mid[:3, :3]).as_rotvec()
    np.testing.assert_allclose(angle, [0, 0, np.pi / 4], atol=1e-9)
    assert traj.pose_at(3.5, max_gap_s=0.5) is None  # 1.5 s from either pose
    assert traj.pose_at(9.0) is None  # after the end


def test_tum_errors_name_the_line(tmp_path):
    (tmp_path / "t.txt").write_text("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"t\.txt:2: time 1.0 is not after the previous"):
        read_tum_trajectory(tmp_path / "t.txt")
    (tmp_path / "q.txt").write_text("1.0 0 0 0 0 0 0 2\n")
    with pytest.raises(ValueError, match=r"q\.txt:1: the quaternion's norm"):
        read_tum_trajectory(tmp_path / "q.txt")
    (tmp_path / "n.txt").write_text("1.0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="expected 8"):
        read_tum_trajectory(tmp_path / "n.txt")


def _room_cloud(rng: np.random.Generator, step: float = 0.05) -> np.ndarray:
    """Points on the six faces of the synthetic BOX_ROOM with 5 mm noise."""
    half = np.array([2.5, 1.3, 3.0])
    faces = []
    for axis in range(3):
        a, b = (i for i in range(3) if i != axis)
        ga, gb = np.meshgrid(np.arange(-half[a], half[a], step),
                             np.arange(-half[b], half[b], step))
        for sign in (-1, 1):
            face = np.zeros((ga.size, 3))
            face[:, a], face[:, b], face[:, axis] = ga.ravel(), gb.ravel(), sign * half[axis]
            faces.append(face)
    cloud = np.concatenate(faces)
    return cloud + rng.normal(0, 0.005, cloud.shape)


def test_calibration_from_a_slam_map(tmp_path, rng):
    camera = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    truth = SensorExtrinsics(Rotation.from_euler("zyx", [-89.0, -1.5, 2.5], degrees=True)
                             .as_matrix(), np.array([-0.03, 0.025, -0.005]))
    frames = synthetic_rig_frames(truth, camera, frames_per_plane=3, mean_noise_m=0.02, seed=4)
    write_synthetic_recording(tmp_path / "rec", frames, camera, with_depth=False)
    cloud_path = write_ply_points(tmp_path / "map.ply", _room_cloud(rng))
    lines = []
    for f in frames:
        quat = Rotation.from_matrix(f.cam_to_world[:3, :3]).as_quat()  # x, y, z, w
        lines.append(" ".join(f"{v:.9f}" for v in (f.zone_frame.timestamp_s,
                                                     *f.cam_to_world[:3, 3], *quat)))
    (tmp_path / "traj.txt").write_text("\n".join(lines) + "\n")
    result = calibrate_recording(Recording(tmp_path / "rec"), nominal_extrinsics(-90.0),
                                 trajectory=read_tum_trajectory(tmp_path / "traj.txt"),
                                 slam_points_world=read_ply_points(cloud_path))
    solved = result.calibration.extrinsics
    error = Rotation.from_matrix(solved.rotation @ truth.rotation.T).magnitude()
    assert np.degrees(error) < 0.5
    assert np.linalg.norm(solved.translation_m - truth.translation_m) < 0.01
    assert result.distance_after_m < result.distance_before_m
    assert not result.skipped
    # A trajectory that covers no frame: the error says why every frame was skipped.
    late = read_tum_trajectory(tmp_path / "traj.txt")
    late = Trajectory(late.times_s + 1e6, late.poses)
    with pytest.raises(ValueError, match=r"usable plane frames.* frames were skipped; the "
                       r"first: frame t=0\.000s: no camera pose near this time\)$"):
        calibrate_recording(Recording(tmp_path / "rec"), nominal_extrinsics(-90.0),
                            trajectory=late, slam_points_world=read_ply_points(cloud_path))


def test_slam_needs_both_files(tmp_path):
    with pytest.raises(ValueError, match="both"):
        calibrate_recording(None, nominal_extrinsics(), trajectory=Trajectory(
            np.zeros(1), np.eye(4)[None]))
