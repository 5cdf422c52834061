"""Pictures without matplotlib (deltar.io.render): OpenCV's colour tables and panels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from deltar.io import render


@pytest.mark.parametrize("name", ["turbo", "magma", "magma_r", "jet"])
def test_opencv_tables_are_matplotlibs_colour_maps(name):
    import matplotlib

    values = np.linspace(0.0, 1.0, 1001)
    ours = render._opencv_table(name)[np.minimum((values * 256).astype(int), 255)]
    theirs = matplotlib.colormaps[name](values)[:, :3]
    # The same maps, tabulated by each library (OpenCV's jet has slightly other knots).
    assert np.abs(ours - theirs).max() < (0.15 if name == "jet" else 0.02)
    assert np.abs(ours - theirs).mean() < (0.03 if name == "jet" else 0.002)


def test_colormap_without_matplotlib_uses_the_opencv_table(monkeypatch):
    monkeypatch.setattr(render, "has_matplotlib", lambda: False)
    out = render.colormap(np.array([[0.0, 0.5, 1.0, 2.0]]), "turbo")
    assert out.shape == (1, 4, 3) and np.all((out >= 0) & (out <= 1))
    np.testing.assert_array_equal(out[0, 2], out[0, 3])  # clipped at 1
    with pytest.raises(ValueError, match="cmap"):
        render.colormap(np.zeros(3), "cividis")


def test_panel_lays_out_tiles_with_titles_and_colour_bars():
    image = np.full((40, 60, 3), 128, np.uint8)
    depth = np.linspace(0.5, 3.0, 40 * 60).reshape(40, 60)
    depth[0, 0] = np.nan
    tiles = [render.Tile(image, "image"), render.scalar_tile(depth, "depth", "turbo", 0.0, 3.0)]
    panel = render.compose_panel(tiles, columns=2, title="frame")
    assert panel.dtype == np.uint8 and panel.ndim == 3
    assert panel.shape[1] >= 2 * 60 and panel.shape[0] >= 40 + 2 * 20
    assert tiles[1].image[0, 0].tolist() == [255, 255, 255]  # NaN left blank


def test_zones_are_drawn_in_their_colours():
    image = np.zeros((32, 32, 3), np.uint8)
    rects = np.array([[0.5, 0.5, 8.5, 8.5], [10.5, 10.5, 20.5, 20.5], [22.5, 22.5, 30.5, 30.5]])
    out = render.draw_zones(image, rects, np.array([True, False, False]),
                            np.array([False, True, False]))
    assert out[1, 4].tolist() == list(render.ZONE_RGB["valid"])
    assert out[11, 15].tolist() == list(render.ZONE_RGB["no_target"])
    assert out[23, 26].tolist() == list(render.ZONE_RGB["invalid"])
    assert image.sum() == 0  # the input is left alone


def test_prediction_panel_without_matplotlib(monkeypatch, tmp_path):
    from deltar.inference.outputs import write_panel
    from deltar.inference.prediction import DepthPrediction
    from deltar.sensor.zone_frame import ZoneFrame

    monkeypatch.setattr(render, "has_matplotlib", lambda: False)
    frame = ZoneFrame(np.full((8, 8), 2.0), np.full((8, 8), 0.05), np.ones((8, 8), bool))
    rects = np.array([[y * 8, x * 8, y * 8 + 8, x * 8 + 8] for y in range(8) for x in range(8)],
                     np.float32)
    prediction = DepthPrediction(depth_m=np.full((64, 64), 2.0, np.float32),
                                 uncertainty_m=np.full((64, 64), 0.1, np.float32),
                                 zone_rects=rects, zone_frame=frame, intrinsics=None,
                                 zones_used=64, network_size=(64, 64))
    path = write_panel(tmp_path / "panel.png", np.zeros((64, 64, 3), np.uint8), prediction,
                       title="test")
    picture = cv2.imread(str(path))
    assert picture is not None and picture.shape[0] > 2 * 64 and picture.shape[1] > 2 * 64
