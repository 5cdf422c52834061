"""Zone patch resampling equals the release's pad / crop / bilinear-resize recipe."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from deltar.models.zone_patches import ZonePatchResampler, zone_window


def _release_recipe(feature_map, rects, stride, n):
    """Independent reference: explicit zero padding, integer crop, F.interpolate."""
    height, width = feature_map.shape[-2:]
    sy = math.trunc(rects[:, 0].min().item() / stride)
    sx = math.trunc(rects[:, 1].min().item() / stride)
    ey = math.trunc(rects[:, 2].max().item() / stride)
    ex = math.trunc(rects[:, 3].max().item() / stride)
    p1 = math.ceil(int((rects[:, 2] - rects[:, 0]).max().item()) / stride)
    p2 = math.ceil(int((rects[:, 3] - rects[:, 1]).max().item()) / stride)
    pad = 64
    padded = F.pad(feature_map, (pad, pad, pad, pad))
    crop = padded[:, :, sy + pad : ey + pad, sx + pad : ex + pad]
    resized = F.interpolate(crop, size=(n * p1, n * p2), mode="bilinear", align_corners=True)
    back = F.interpolate(resized, size=crop.shape[-2:], mode="bilinear", align_corners=True)
    canvas = torch.zeros_like(padded)
    canvas[:, :, sy + pad : ey + pad, sx + pad : ex + pad] = back
    return resized, canvas[:, :, pad : pad + height, pad : pad + width], (p1, p2)


@pytest.mark.parametrize(
    ("offset", "stride", "n"),
    [((-13.4, 70.2), 4, 8), ((16.0, 96.0), 8, 8), ((40.5, -20.25), 16, 8), ((-3.0, 5.5), 8, 4)],
)
def test_gather_and_scatter_match_release_recipe(offset, stride, n, rects_on_grid):
    torch.manual_seed(0)
    rects = rects_on_grid(480, 640, n, offset=offset, span=(62.1 * n, 57.3 * n))
    feature_map = torch.randn(1, 5, 480 // stride, 640 // stride)
    map_size = (480 // stride, 640 // stride)
    resampler = ZonePatchResampler(zone_window(rects[None], stride, n), map_size, torch.float32)
    resized, pasted, (p1, p2) = _release_recipe(feature_map, rects, stride, n)
    assert resampler.window.patch == (p1, p2)
    tokens = resampler.gather(feature_map)
    expected_tokens = resized.reshape(1, 5, n, p1, n, p2).permute(0, 2, 4, 3, 5, 1)
    torch.testing.assert_close(tokens, expected_tokens.reshape(n * n, p1 * p2, 5),
                               atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(resampler.scatter(tokens, 1), pasted, atol=1e-5, rtol=1e-5)


def test_zones_wholly_outside_give_zero_patches_and_nothing_back(rects_on_grid):
    rects = rects_on_grid(64, 96, 4, offset=(200.0, 300.0))
    resampler = ZonePatchResampler(zone_window(rects[None], 4, 4), (16, 24), torch.float32)
    tokens = resampler.gather(torch.randn(1, 3, 16, 24))
    assert torch.count_nonzero(tokens) == 0
    assert torch.count_nonzero(resampler.scatter(torch.ones_like(tokens), 1)) == 0


def test_per_sample_layouts_are_independent(rects_on_grid):
    torch.manual_seed(1)
    first = rects_on_grid(64, 96, 8, offset=(-4.0, 2.0), span=(64, 80))
    second = rects_on_grid(64, 96, 8, offset=(10.0, -12.0), span=(48, 96))
    feature_map = torch.randn(2, 4, 16, 24)
    both = ZonePatchResampler(zone_window(torch.stack([first, second]), 4, 8), (16, 24),
                              torch.float32)
    alone = ZonePatchResampler(zone_window(second[None], 4, 8), (16, 24), torch.float32)
    # Both layouts need (2, 3)-token patches, so the second sample's patches must not
    # depend on the first sample's layout.
    assert both.window.patch == alone.window.patch == (2, 3)
    torch.testing.assert_close(both.gather(feature_map)[64:], alone.gather(feature_map[1:]))
    # Pasting the second sample's patches back never touches the first sample.
    tokens = both.gather(feature_map)
    tokens[:64] = 0
    assert torch.count_nonzero(both.scatter(tokens, 2)[0]) == 0


@pytest.mark.parametrize(("offset", "stride"), [((-13.4, 70.2), 4), ((40.5, -20.25), 16)])
def test_traceable_matrices_equal_the_eager_ones(offset, stride, rects_on_grid):
    # The export path (one-hot products, trunc as sign * floor |x|) builds the same
    # resampling, including windows starting before the map (negative coordinates).
    rects = torch.stack([rects_on_grid(480, 640, 8, offset=offset, span=(500.0, 460.0)),
                         rects_on_grid(480, 640, 8, offset=(-offset[1], 3.0))])
    window = zone_window(rects, stride, 8)
    assert (window.start < 0).any()
    size = (480 // stride, 640 // stride)
    eager = ZonePatchResampler(window, size, torch.float32)
    traced = ZonePatchResampler(window, size, torch.float32, traceable=True)
    for name in ("rows_in", "cols_in", "rows_out", "cols_out"):
        torch.testing.assert_close(getattr(traced, name), getattr(eager, name), atol=0, rtol=0)
    values = torch.tensor([-2.5, -2.0, -0.4, 0.0, 0.4, 2.0, 2.7])
    from deltar.models.zone_patches import _trunc

    assert torch.equal(_trunc(values), values.trunc())
