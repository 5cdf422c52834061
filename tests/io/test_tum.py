"""The TUM trajectory reader shared by calibration and mapping."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.io.tum import quaternion_pose, read_tum_poses


def test_poses_times_and_quaternion_order(tmp_path):
    s = np.sqrt(0.5)
    path = tmp_path / "traj.txt"
    path.write_text("# t tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n"
                    f"2.5, 1, 2, 3, 0, 0, {s}, {s}  # 90 deg about z\n")
    times, poses = read_tum_poses(path)
    np.testing.assert_array_equal(times, [1.0, 2.5])
    assert poses.shape == (2, 4, 4) and poses.dtype == np.float64
    np.testing.assert_allclose(poses[1][:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(poses[1][:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(poses[0], np.eye(4))


@pytest.mark.parametrize("text, message", [
    ("0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0\n", r"t.txt:2: expected 8 numbers"),
    ("0 0 0 0 0 0 0 2\n", r"t.txt:1: the quaternion's norm is 2.0000, not 1"),
    ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r"t.txt:2: time 1.0 is not after the previous"),
    ("0 a 0 0 0 0 0 1\n", r"t.txt:1: expected 't tx ty tz qx qy qz qw'"),
    ("nan 0 0 0 0 0 0 1\n", r"t.txt:1: the time is not a finite number"),
    ("# nothing\n", r"no pose lines"),
])
def test_bad_lines_name_the_file_and_line(tmp_path, text, message):
    path = tmp_path / "t.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_tum_poses(path)


def test_missing_file_and_non_finite_pose(tmp_path):
    with pytest.raises(FileNotFoundError, match="trajectory file not found"):
        read_tum_poses(tmp_path / "missing.txt")
    with pytest.raises(ValueError, match="here: the pose has NaN"):
        quaternion_pose(np.array([0.0, np.nan, 0.0]), np.array([0, 0, 0, 1.0]), "here")
