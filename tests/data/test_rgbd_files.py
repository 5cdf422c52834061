"""Single RGB-D files: depth images in metres with invalid values as 0, colour images
that are corrupt or missing named in the error."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from deltar.data.rgbd_files import check_depth_scale, read_color, read_depth


def _write_png16(path, array):
    Image.fromarray(array.astype(np.uint16)).save(path)


def test_invalid_depth_values_become_zero(tmp_path):
    raw = np.array([[0, 1000, 65535], [2500, 5000, 1]], dtype=np.uint16)
    _write_png16(tmp_path / "d.png", raw)
    depth = read_depth(tmp_path / "d.png", depth_scale=1000.0)
    np.testing.assert_allclose(depth, [[0.0, 1.0, 0.0], [2.5, 5.0, 0.001]], rtol=1e-6)
    np.save(tmp_path / "d.npy", np.array([[np.nan, 2.0], [np.inf, -1.0]], np.float32))
    np.testing.assert_array_equal(read_depth(tmp_path / "d.npy", 1.0), [[0, 2], [0, 0]])


def test_corrupt_and_missing_colour_images_name_the_file(tmp_path, rng):
    good = tmp_path / "good.jpg"
    Image.fromarray(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)).save(good)
    truncated = tmp_path / "truncated.jpg"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ValueError, match=r"truncated\.jpg"):
        read_color(truncated)
    with pytest.raises(FileNotFoundError, match=r"missing\.png"):
        read_color(tmp_path / "missing.png")


def test_depth_scale_must_be_finite_and_positive(tmp_path):
    assert check_depth_scale(1000) == 1000.0 and isinstance(check_depth_scale(1000), float)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="depth_scale must be finite and > 0"):
            check_depth_scale(bad)
    with pytest.raises(ValueError, match="depth_scale must be finite and > 0, got 0"):
        read_depth(tmp_path / "missing.png", 0)


def test_8_bit_boolean_and_complex_depth_images_are_refused(tmp_path):
    """An 8-bit PNG holds at most 0.255 m in millimetres: a picture, not a depth map."""
    Image.fromarray(np.full((4, 6), 200, np.uint8)).save(tmp_path / "grey.png")
    np.save(tmp_path / "mask.npy", np.ones((4, 6), bool))
    np.save(tmp_path / "complex.npy", np.ones((4, 6), complex))
    for name, dtype in (("grey.png", "uint8"), ("mask.npy", "bool"),
                        ("complex.npy", "complex128")):
        with pytest.raises(ValueError, match=rf"depth image \S*{name} holds {dtype} values"):
            read_depth(tmp_path / name, 1000.0)


def test_float_depth_in_metres_read_with_a_millimetre_scale_is_refused(tmp_path):
    metres = np.full((4, 6), 2.5, dtype=np.float32)
    metres[0, 0] = np.nan
    np.save(tmp_path / "m.npy", metres)
    with pytest.raises(ValueError, match=r"m\.npy: float values up to 2\.5 read as at most "
                                         r"2\.5 mm with depth_scale 1000; if they are "
                                         r"metres, set depth_scale to 1"):
        read_depth(tmp_path / "m.npy", 1000.0)
    assert read_depth(tmp_path / "m.npy", 1.0)[1, 1] == pytest.approx(2.5)
    # Float millimetres with their scale, and an all-invalid frame, read as before.
    np.save(tmp_path / "mm.npy", metres * 1000)
    assert read_depth(tmp_path / "mm.npy", 1000.0)[1, 1] == pytest.approx(2.5)
    np.save(tmp_path / "none.npy", np.zeros((4, 6), np.float32))
    assert not read_depth(tmp_path / "none.npy", 1000.0).any()
