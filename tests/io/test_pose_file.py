"""Pose files: the one reader, writer and check of a 4x4 camera-to-world text file."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.io.pose_file import check_pose, frame_pose_file, read_pose_file, write_pose_file


def _pose(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    pose[:3, 3] = rng.uniform(-3.0, 3.0, 3)
    return pose


def test_a_pose_round_trips_and_is_never_overwritten(tmp_path):
    path = tmp_path / "pose" / "33333333.txt"
    path.parent.mkdir()
    write_pose_file(path, _pose(1))
    np.testing.assert_allclose(read_pose_file(path), _pose(1), atol=1e-9)
    with pytest.raises(FileExistsError):
        write_pose_file(path, _pose(2))
    np.testing.assert_allclose(read_pose_file(path), _pose(1), atol=1e-9)


def test_a_pose_written_with_four_decimals_reads_as_an_exact_rotation(tmp_path):
    pose = _pose(4)
    rounded = np.round(pose, 4)
    (tmp_path / "rounded.txt").write_text(
        "\n".join(" ".join(f"{v:.4f}" for v in row) for row in rounded) + "\n")
    read = read_pose_file(tmp_path / "rounded.txt")
    np.testing.assert_allclose(read[:3, :3].T @ read[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(read, pose, atol=2e-4)  # the nearest rotation: the pose's
    assert np.array_equal(read[:3, 3], rounded[:3, 3])  # the translation as written
    kept = rounded.copy()
    check_pose(kept, "caller's array")
    assert np.array_equal(kept, rounded)  # the caller's array is not changed


def test_transforms_that_are_not_rigid_are_refused_by_name(tmp_path):
    scaled = _pose(3)
    scaled[:3, :3] *= 2.0
    with pytest.raises(ValueError, match=r"scaled.txt: the pose's 3x3 block is not a rotation"):
        write_pose_file(tmp_path / "scaled.txt", scaled)
    assert not (tmp_path / "scaled.txt").exists()
    (tmp_path / "mirror.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"mirror.txt: .*det = -1"):
        read_pose_file(tmp_path / "mirror.txt")
    (tmp_path / "short.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(ValueError, match=r"short.txt: a pose must be a 4x4 matrix"):
        read_pose_file(tmp_path / "short.txt")
    (tmp_path / "words.txt").write_text("one two\n")
    with pytest.raises(ValueError, match=r"words.txt: not a 4x4 matrix of numbers"):
        read_pose_file(tmp_path / "words.txt")
    with pytest.raises(ValueError, match="NaN"):
        check_pose(np.full((4, 4), np.nan), "nan")
    with pytest.raises(ValueError, match="last row"):
        check_pose(np.vstack([_pose(4)[:3], [0.0, 0.0, 1.0, 1.0]]), "row")
    with pytest.raises(FileNotFoundError, match=r"missing\.txt"):
        read_pose_file(tmp_path / "missing.txt")


def test_a_frames_pose_file_in_both_folder_layouts(tmp_path):
    (tmp_path / "pose").mkdir()
    write_pose_file(tmp_path / "pose" / "000007.txt", _pose(5))
    write_pose_file(tmp_path / "frame-000002.pose.txt", _pose(6))
    assert frame_pose_file(tmp_path, "000007") == tmp_path / "pose" / "000007.txt"
    assert frame_pose_file(tmp_path, "frame-000002") == tmp_path / "frame-000002.pose.txt"
    assert frame_pose_file(tmp_path, "000008") is None


def test_an_empty_pose_file_is_one_error_without_numpys_warning(tmp_path):
    path = tmp_path / "0.txt"
    path.write_text("")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "input contained no data" would raise
        with pytest.raises(ValueError, match=r"0\.txt: a pose must be a 4x4 matrix"):
            read_pose_file(path)
