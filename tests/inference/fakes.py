"""Stand-ins for the estimator's tests: a tiny DeltarNet whose output can be predicted
by hand, random images and zone frames."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from deltar.sensor.zone_frame import ZoneFrame


def random_frame(rng: np.random.Generator, grid: int = 8, invalid: int = 3) -> ZoneFrame:
    """A grid x grid zone frame, means 0.8-3.5 m, ``invalid`` zones invalid at random."""
    mean = rng.uniform(0.8, 3.5, size=(grid, grid))
    sigma = rng.uniform(0.01, 0.1, size=(grid, grid))
    valid = np.ones((grid, grid), bool)
    valid.flat[rng.choice(grid * grid, invalid, replace=False)] = False
    return ZoneFrame(np.where(valid, mean, 0), np.where(valid, sigma, 0), valid)


def random_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """An (height, width, 3) uint8 RGB image of uniform noise."""
    return rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)


class ZonePainterNet(nn.Module):
    """Paints each valid zone's mean hypothesis over the half-resolution cells it covers.

    A half-resolution cell (i, j) has its centre at network-input pixel (2i + 0.5,
    2j + 0.5); it takes the value of the zone whose rectangle contains that point
    (half-open), else 0. Uncertainty is a constant 0.1 m. Same call signature and
    outputs as ``DeltarNet.forward``.
    """

    def __init__(self, num_hypotheses: int = 16) -> None:
        super().__init__()
        #: What :meth:`contract` returns (tests set ``design_size`` here).
        self.contract_values = {"num_hypotheses": num_hypotheses}
        self.dummy = nn.Parameter(torch.zeros(()))  # so .to(dtype) has something to move

    def contract(self) -> dict:
        """The input contract, as ``DeltarNet.contract``."""
        return dict(self.contract_values)

    def forward(self, image, hypotheses, zone_rects, zone_valid):
        batch, _, height, width = image.shape
        ys = torch.arange(height // 2, dtype=torch.float32) * 2 + 0.5
        xs = torch.arange(width // 2, dtype=torch.float32) * 2 + 0.5
        rects = zone_rects.float()
        in_y = (ys >= rects[..., 0:1]) & (ys < rects[..., 2:3])  # (B, Z, h)
        in_x = (xs >= rects[..., 1:2]) & (xs < rects[..., 3:4])  # (B, Z, w)
        value = hypotheses.float().mean(-1) * zone_valid
        depth = torch.einsum("bzh,bzw,bz->bhw", in_y.float(), in_x.float(), value)
        depth = depth[:, None].to(image.dtype) + self.dummy.to(image.dtype)
        return {"depth": depth, "bin_edges": torch.zeros(batch, 3),
                "uncertainty": torch.full_like(depth, 0.1)}
