"""Pose readers (folder, TUM, bag), checks, matching to frames, ATE."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.io.tum import quaternion_pose
from deltar.mapping.poses import (
    absolute_trajectory_error,
    interpolate_poses,
    match_poses,
    read_bag_poses,
    read_pose_folder,
    read_tum_trajectory,
    write_tum_trajectory,
)
from tests.mapping.conftest import pose_at


def _write(path, pose):
    path.write_text("\n".join(" ".join(f"{v:.9f}" for v in row) for row in pose) + "\n")


def test_a_folder_of_pose_files_in_both_layouts(tmp_path):
    (tmp_path / "a").mkdir()
    _write(tmp_path / "a" / "000001.txt", pose_at(0.5))
    _write(tmp_path / "a" / "000000.txt", pose_at(0.0))
    found = read_pose_folder(tmp_path / "a")
    assert found.names == ("000000", "000001")
    assert found.poses[1, 0, 3] == pytest.approx(0.5)
    (tmp_path / "b").mkdir()
    _write(tmp_path / "b" / "frame-000002.pose.txt", pose_at(0.2, yaw_deg=10))
    (tmp_path / "b" / "frame-000002.color.jpg").write_bytes(b"")
    found = read_pose_folder(tmp_path / "b")
    assert found.names == ("frame-000002",)


def test_the_shared_scenes_poses_read(shared_data):
    cabinet = read_pose_folder(shared_data / "tum_fr3_cabinet" / "pose")
    assert len(cabinet.names) == 58
    kitchen = read_pose_folder(shared_data / "7scenes_redkitchen")
    assert kitchen.names[0] == "frame-000000" and len(kitchen.names) > 100


def test_poses_that_are_not_rotations_are_refused(tmp_path):
    bad = pose_at(0.0)
    bad[:3, :3] *= 2.0
    _write(tmp_path / "000000.txt", bad)
    with pytest.raises(ValueError, match=r"000000.txt: the pose's 3x3 block is not a rotation"):
        read_pose_folder(tmp_path)


def test_tum_trajectory_reads_interpolates_and_round_trips(tmp_path):
    times = np.array([0.0, 0.1, 0.2])
    poses = np.stack([pose_at(0.0), pose_at(0.1, yaw_deg=10), pose_at(0.2, yaw_deg=20)])
    path = write_tum_trajectory(tmp_path / "t.txt", times, poses)
    found = read_tum_trajectory(path)
    np.testing.assert_allclose(found.poses, poses, atol=1e-7)
    middle, covered = interpolate_poses(found, np.array([0.05, 0.5]))
    assert covered.tolist() == [True, False]
    assert middle[0, 0, 3] == pytest.approx(0.05)
    yaw = Rotation.from_matrix(middle[0, :3, :3]).as_euler("yxz", degrees=True)[0]
    assert yaw == pytest.approx(5.0, abs=1e-6)


def test_tum_errors_name_the_line(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("# comment\n0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match=r"t.txt:3: expected 8 numbers"):
        read_tum_trajectory(path)
    path.write_text("0 0 0 0 0 0 0 2\n")
    with pytest.raises(ValueError, match=r"t.txt:1: the quaternion's norm is 2.0000, not 1"):
        read_tum_trajectory(path)
    path.write_text("1 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="not after the previous"):
        read_tum_trajectory(path)
    with pytest.raises(FileNotFoundError, match="trajectory file not found"):
        read_tum_trajectory(tmp_path / "missing.txt")


def test_a_trajectory_that_covers_no_frame_is_refused(tmp_path):
    path = write_tum_trajectory(tmp_path / "t.txt", np.array([100.0, 100.1]),
                                np.stack([pose_at(0.0), pose_at(0.1)]))
    with pytest.raises(ValueError, match=r"covers none of the frames \(poses 100.000..100.100 s, "
                                         r"frames 0.000..0.200 s\)"):
        match_poses(read_tum_trajectory(path), np.array([0.0, 0.1, 0.2]), ["a", "b", "c"])
    (tmp_path / "p").mkdir()
    _write(tmp_path / "p" / "other.txt", pose_at(0.0))
    with pytest.raises(ValueError, match="no pose file is named like a frame"):
        match_poses(read_pose_folder(tmp_path / "p"), np.zeros(1), ["frame"])


def test_a_gap_in_the_trajectory_covers_nothing_inside_it(tmp_path):
    times = np.array([0.0, 0.1, 0.2, 5.0, 5.1])
    path = write_tum_trajectory(tmp_path / "t.txt", times, np.stack([pose_at(t) for t in times]))
    _, covered = interpolate_poses(read_tum_trajectory(path), np.array([0.15, 2.5, 5.05]))
    assert covered.tolist() == [True, False, True]


def _bag_with_poses(path, *, tf: bool, topic: str = "/camera/pose"):
    from deltar.io.ros_messages import stamped_header, typestore
    from deltar.io.rosbag_writer import BagWriter

    types = typestore().types
    with BagWriter(path) as writer:
        for i in range(3):
            stamp = 1_000_000_000 + i * 100_000_000
            q = Rotation.from_euler("y", 10 * i, degrees=True).as_quat()
            orientation = types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])
            if tf:
                moving = types["geometry_msgs/msg/TransformStamped"](
                    header=stamped_header(stamp, "odom"), child_frame_id="base",
                    transform=types["geometry_msgs/msg/Transform"](
                        translation=types["geometry_msgs/msg/Vector3"](x=0.1 * i, y=0.0,
                                                                       z=0.0),
                        rotation=orientation))
                writer._write("/tf", "tf2_msgs/msg/TFMessage",
                              types["tf2_msgs/msg/TFMessage"](transforms=[moving]), stamp)
            else:
                writer.add_pose(topic, stamp, "map", quaternion_pose([0.1 * i, 0.0, 0.0], q,
                                                                     "test"))
        if tf:  # the camera sits 0.2 m above the base
            static = types["geometry_msgs/msg/TransformStamped"](
                header=stamped_header(1_000_000_000, "base"), child_frame_id="camera",
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](x=0.0, y=-0.2, z=0.0),
                    rotation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                   w=1.0)))
            writer._write("/tf_static", "tf2_msgs/msg/TFMessage",
                          types["tf2_msgs/msg/TFMessage"](transforms=[static]), 1_000_000_000)
    return path


def test_bag_pose_topic_and_tf_chain(tmp_path):
    pytest.importorskip("rosbags")
    found = read_bag_poses(_bag_with_poses(tmp_path / "a", tf=False), pose_topic="/camera/pose")
    assert found.times_s.tolist() == pytest.approx([1.0, 1.1, 1.2])
    assert found.poses[2, 0, 3] == pytest.approx(0.2)
    chained = read_bag_poses(_bag_with_poses(tmp_path / "b", tf=True), camera_frame="camera")
    assert len(chained.times_s) == 3
    # camera = odom_T_base(i) @ base_T_camera: the 0.2 m offset is rotated by the yaw.
    np.testing.assert_allclose(chained.poses[0, :3, 3], [0.0, -0.2, 0.0], atol=1e-9)
    np.testing.assert_allclose(chained.poses[2, :3, 3], [0.2, -0.2, 0.0], atol=1e-9)
    with pytest.raises(ValueError, match="no transform chain from the camera frame 'lens'"):
        read_bag_poses(tmp_path / "b", camera_frame="lens")
    with pytest.raises(ValueError, match="expected geometry_msgs/msg/PoseStamped"):
        read_bag_poses(tmp_path / "b", pose_topic="/tf")
    # deltar record's own pose topic needs no --pose-topic; a topic of another name does.
    own = read_bag_poses(tmp_path / "a", camera_frame="camera")
    np.testing.assert_allclose(own.poses, found.poses)
    other = _bag_with_poses(tmp_path / "c", tf=False, topic="/robot/pose")
    assert read_bag_poses(other, camera_frame="camera") is None  # none: odometry


def test_ate_is_zero_for_a_rigidly_moved_copy_and_measures_drift():
    reference = np.stack([pose_at(0.1 * i, yaw_deg=3 * i) for i in range(6)])
    moved = np.einsum("ij,njk->nik", pose_at(1.0, 2.0, yaw_deg=40), reference)
    assert absolute_trajectory_error(moved, reference) == pytest.approx(0.0, abs=1e-9)
    drifted = reference.copy()
    drifted[:, 1, 3] += np.linspace(0, 0.1, 6) ** 2 * 10  # a bend alignment cannot undo
    assert absolute_trajectory_error(drifted, reference) > 0.01


def test_a_frame_at_a_poses_own_time_gets_it_across_a_gap(tmp_path):
    """5.0 is a pose's time after a gap: it has that pose (it was left out)."""
    times = np.array([0.0, 0.1, 0.2, 5.0, 5.1])
    path = write_tum_trajectory(tmp_path / "t.txt", times, np.stack([pose_at(t) for t in times]))
    poses, covered = interpolate_poses(read_tum_trajectory(path), np.array([0.2, 2.5, 5.0]))
    assert covered.tolist() == [True, False, True]
    assert poses[2, 0, 3] == pytest.approx(5.0)


def test_the_pose_folders_names_are_given_in_numeric_order(tmp_path):
    (tmp_path / "p").mkdir()
    for name in ("5", "10", "9"):
        _write(tmp_path / "p" / f"{name}.txt", pose_at(0.0))
    with pytest.raises(ValueError, match=r"poses 5\.\.10, frames 2\.\.11\)"):
        match_poses(read_pose_folder(tmp_path / "p"), np.zeros(2), ["11", "2"])
