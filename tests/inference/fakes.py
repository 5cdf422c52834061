"""A tiny stand-in for DeltarNet with an output that can be predicted by hand."""

from __future__ import annotations

import torch
from torch import nn


class ZonePainterNet(nn.Module):
    """Paints each valid zone's mean hypothesis over the half-resolution cells it covers.

    A half-resolution cell (i, j) has its centre at network-input pixel (2i + 0.5,
    2j + 0.5); it takes the value of the zone whose rectangle contains that point
    (half-open), else 0. Uncertainty is a constant 0.1 m. Same call signature and
    outputs as ``DeltarNet.forward``.
    """

    def __init__(self, num_hypotheses: int = 16) -> None:
        super().__init__()
        self.config = {"num_hypotheses": num_hypotheses}
        self.dummy = nn.Parameter(torch.zeros(()))  # so .to(dtype) has something to move

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
