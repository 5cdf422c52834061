"""deltar.io.ply: round trips and bad files named in the error."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.io.ply import read_ply, write_ply


@pytest.fixture
def cloud():
    rng = np.random.default_rng(3)
    points = rng.uniform(-2, 4, (5, 3)).astype(np.float32)
    colors = rng.integers(0, 256, (5, 3), dtype=np.uint8)
    return points, colors


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_with_colours_and_comments(tmp_path, cloud, binary):
    points, colors = cloud
    path = write_ply(tmp_path / "c.ply", points, colors, comments=["one", "two\nlines"],
                     binary=binary)
    read = read_ply(path)
    np.testing.assert_allclose(read.points, points, atol=1e-6)
    np.testing.assert_array_equal(read.colors, colors)
    assert read.points.dtype == np.float64 and read.colors.dtype == np.uint8
    assert read.comments == ["one", "two lines"]


def test_points_only_and_empty(tmp_path, cloud):
    read = read_ply(write_ply(tmp_path / "p.ply", cloud[0]))
    assert read.colors is None and read.comments == []
    points, colors, _ = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3))))
    assert points.shape == (0, 3) and colors is None


def test_refuses_to_overwrite(tmp_path, cloud):
    path = write_ply(tmp_path / "c.ply", cloud[0])
    with pytest.raises(FileExistsError):
        write_ply(path, cloud[0])
    write_ply(path, cloud[0][:2], overwrite=True)
    assert len(read_ply(path).points) == 2


@pytest.mark.parametrize(("content", "message"), [
    (b"hello", "not a PLY file"),
    (b"ply\nformat binary_big_endian 1.0\nelement vertex 0\nend_header\n",
     "unsupported PLY format 'binary_big_endian'"),
    (b"ply\nformat ascii 1.0\nelement vertex x\nend_header\n", "malformed PLY header line"),
    (b"ply\nformat ascii 1.0\nelement face 1\nend_header\n", "no vertex element"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n",
     "no x, y, z"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n",
     "unknown PLY property type 'half'"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n1 2 3\n", "truncated PLY: 1 of 2 vertices"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
     b"property float y\nproperty float z\nend_header\n" + b"\0" * 13, "truncated PLY"),
])
def test_bad_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as info:
        read_ply(path)
    assert str(info.value).startswith(f"{path}: ")


def test_missing_file_and_bad_arrays(tmp_path, cloud):
    with pytest.raises(FileNotFoundError, match=r"none\.ply"):
        read_ply(tmp_path / "none.ply")
    with pytest.raises(ValueError, match=r"points must be an \(N, 3\) array"):
        write_ply(tmp_path / "x.ply", np.zeros((4, 2)))
    with pytest.raises(ValueError, match="colors must be"):
        write_ply(tmp_path / "x.ply", cloud[0], cloud[1][:2])
