"""Output writers: 16-bit PNG, npy, colour PNG, PLY point cloud, panel, refusal to overwrite."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics
from deltar.inference.outputs import (
    OUTPUT_KINDS,
    colorize,
    depth_to_png16,
    depth_to_points,
    write_depth_npy,
    write_depth_png16,
    write_ply,
    write_prediction,
)
from deltar.inference.prediction import DepthPrediction
from deltar.io.ply import read_ply
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import random_frame


def test_png16_is_millimetres_with_zero_for_invalid(tmp_path):
    depth = np.array([[1.2346, 0.0, np.nan], [np.inf, 70.0, 0.0004]], np.float32)
    expected = np.array([[1235, 0, 0], [0, 65535, 0]], np.uint16)  # 1234.6 mm -> 1235
    np.testing.assert_array_equal(depth_to_png16(depth), expected)
    path = write_depth_png16(tmp_path / "d.png", depth)
    with Image.open(path) as img:
        read = np.asarray(img)
    np.testing.assert_array_equal(read.astype(np.uint16), expected)
    with pytest.raises(FileExistsError):
        write_depth_png16(path, depth)


def test_npy_round_trip(tmp_path, rng):
    depth = rng.uniform(0.5, 4, (5, 7)).astype(np.float32)
    path = write_depth_npy(tmp_path / "d.npy", depth)
    np.testing.assert_array_equal(np.load(path), depth)
    with pytest.raises(ValueError, match="depth_m"):
        write_depth_npy(tmp_path / "e.npy", depth[None])


def test_colorize_range_and_invalid():
    rgb = colorize(np.array([[0.0, 1.0, 2.0, np.nan]]), vmin=0.0, vmax=2.0)
    assert rgb.shape == (1, 4, 3) and rgb.dtype == np.uint8
    import matplotlib

    turbo = matplotlib.colormaps["turbo"]
    np.testing.assert_array_equal(rgb[0, 0], (np.array(turbo(0.0)[:3]) * 255 + 0.5).astype(int))
    np.testing.assert_array_equal(rgb[0, 2], (np.array(turbo(1.0)[:3]) * 255 + 0.5).astype(int))
    np.testing.assert_array_equal(rgb[0, 3], [0, 0, 0])
    with pytest.raises(ValueError, match="unknown colour map 'bogus'"):
        colorize(np.ones((2, 2)), cmap="bogus")  # was matplotlib's KeyError


def test_point_cloud_back_projection_by_hand():
    intr = CameraIntrinsics(2.0, 4.0, 0.5, 0.5, 2, 2)
    depth = np.array([[1.0, 2.0], [0.0, 4.0]], np.float32)
    image = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    points, colors = depth_to_points(depth, intr, image)
    # (u, v) = (0, 0): x = (0 - 0.5) / 2 * 1, y = (0 - 0.5) / 4 * 1.
    expected = np.array([[-0.25, -0.125, 1.0], [0.5, -0.25, 2.0], [1.0, 0.5, 4.0]])
    np.testing.assert_allclose(points, expected, atol=1e-6)
    np.testing.assert_array_equal(colors, image.reshape(4, 3)[[0, 1, 3]])


def test_ply_binary_little_endian_with_intrinsics(tmp_path):
    intr = CameraIntrinsics(500.5, 501.0, 319.5, 239.5, 640, 480)
    points = np.array([[0.1, -0.2, 1.5], [1.0, 2.0, 3.0]], np.float32)
    colors = np.array([[255, 0, 10], [1, 2, 3]], np.uint8)
    path = write_ply(tmp_path / "c.ply", points, colors, intr)
    raw = path.read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\n")
    # 15 bytes per vertex: 3 little-endian float32 + 3 uchar.
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n"):]
    assert len(body) == 2 * 15
    assert np.frombuffer(body[:12], "<f4").tolist() == pytest.approx([0.1, -0.2, 1.5])
    assert list(body[12:15]) == [255, 0, 10]
    read_points, read_colors, comments = read_ply(path)
    np.testing.assert_array_equal(read_points, points)
    np.testing.assert_array_equal(read_colors, colors)
    assert "intrinsics 500.5 501.0 319.5 239.5 640 480" in comments


def _prediction(rng, height=32, width=48):
    valid = np.ones((4, 4), bool)
    valid[0, :2] = False  # one zone with no target, one invalid otherwise: both drawn
    frame = ZoneFrame(rng.uniform(1, 3, (4, 4)) * valid, np.full((4, 4), 0.02), valid,
                      no_target=~valid & (np.arange(16).reshape(4, 4) == 0))
    rects = np.array([[r * 8 - 0.5, c * 12 - 0.5, r * 8 + 7.5, c * 12 + 11.5]
                      for r in range(4) for c in range(4)], np.float32)
    return DepthPrediction(depth_m=rng.uniform(1, 3, (height, width)).astype(np.float32),
                           uncertainty_m=np.full((height, width), 0.05, np.float32),
                           zone_rects=rects, zone_frame=frame,
                           intrinsics=CameraIntrinsics(40, 40, 23.5, 15.5, width, height))


def test_write_prediction_writes_every_kind_and_refuses_existing(tmp_path, rng):
    pred = _prediction(rng)
    image = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
    paths = write_prediction(tmp_path, "frame", image, pred, title="test")
    assert set(paths) == set(OUTPUT_KINDS)
    for path in paths.values():
        assert path.is_file() and path.stat().st_size > 0
    with Image.open(paths["panel"]) as img:
        assert img.size[0] > 100
    np.testing.assert_array_equal(np.load(paths["npy"]), pred.depth_m)
    points, _, _ = read_ply(paths["ply"])
    assert points.shape == (32 * 48, 3)
    before = paths["png16"].read_bytes()
    with pytest.raises(FileExistsError):
        write_prediction(tmp_path, "frame", image, pred, kinds=("png16",))
    assert paths["png16"].read_bytes() == before
    with pytest.raises(ValueError, match="unknown output kinds"):
        write_prediction(tmp_path, "x", image, pred, kinds=("jpeg",))


def test_the_panel_draws_the_flags_the_prediction_used(rng):
    from deltar.inference.outputs import _panel_zones_and_range

    frame = random_frame(rng, invalid=8)  # carries no flags
    used = ~frame.valid.reshape(-1)
    prediction = DepthPrediction(depth_m=np.ones((8, 8), np.float32),
                                 uncertainty_m=np.ones((8, 8), np.float32),
                                 zone_rects=np.zeros((64, 4), np.float32), zone_frame=frame,
                                 intrinsics=ZJU_L5_INTRINSICS, zone_no_target=used)
    _, _, far, _, title = _panel_zones_and_range(prediction)
    np.testing.assert_array_equal(far, used)
    assert "no target" in title


def test_write_prediction_checks_everything_before_its_first_file(tmp_path, rng):
    pred = _prediction(rng)
    image = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
    for bad, message in ((image[:16], r"image must be .* 32x48|image .*32"),
                         (image[..., 0], "image must be an .H, W, 3. uint8 RGB image")):
        with pytest.raises(ValueError, match=message):
            write_prediction(tmp_path / "out", "frame", bad, pred)
    with pytest.raises(ValueError, match="prediction must be a DepthPrediction, got dict"):
        write_prediction(tmp_path / "out", "frame", image, {"depth_m": 1})
    with pytest.raises(ValueError, match="stem must be a file name without folders"):
        write_prediction(tmp_path / "out", "../frame", image, pred)
    assert not (tmp_path / "out").exists() and list(tmp_path.iterdir()) == []
