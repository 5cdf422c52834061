"""Per-zone histograms: bins as torch.histc's, pixel bounds as the geometry's."""

from __future__ import annotations

import numpy as np
import torch

from deltar.sensor.geometry import zone_rects_to_pixel_bounds
from deltar.sensor.simulator_config import SimulatorConfig
from deltar.sensor.zone_histograms import depth_bin_index, zone_pixel_bounds

BIN = 0.04


def test_bin_index_matches_torch_histc():
    gen = torch.Generator().manual_seed(0)
    edges = torch.arange(101, dtype=torch.float64) * BIN
    values = torch.cat([edges.float(), (edges + 1e-7).float(), (edges - 1e-7).float(),
                        torch.rand(20000, generator=gen) * 4.2,
                        torch.arange(0, 4001, dtype=torch.float32) / 1000.0])
    values = values[(values > 0) & (values <= 4.0)]
    index = depth_bin_index(values, SimulatorConfig())
    expected = torch.stack([torch.histc(v[None], bins=100, min=0, max=4.0).argmax()
                            for v in values])
    assert torch.equal(index.long(), expected)


def test_pixel_bounds_match_geometry(rng):
    rects = rng.uniform(-100, 700, size=(200, 4)).astype(np.float32)
    rects[:, 2:] = rects[:, :2] + rng.uniform(0, 120, size=(200, 2))
    ours = zone_pixel_bounds(torch.from_numpy(rects), 480, 640).numpy()
    assert np.array_equal(ours, zone_rects_to_pixel_bounds(rects, 480, 640))
