"""No refinement (the paper's ablation): depth regressed directly from the features."""

from __future__ import annotations

import torch
from torch import nn

from deltar.models.heads.base import DepthHead, HeadOutput, ZoneInputs


class DirectDepthHead(DepthHead):
    """No refinement (ablation): a 3x3 convolution and a sigmoid scaled to the depth range.

    Args:
        in_channels: input feature width.
        min_depth: smallest output depth, metres.
        max_depth: largest output depth, metres.
    """

    def __init__(self, in_channels: int, min_depth: float, max_depth: float) -> None:
        super().__init__()
        self.min_depth = min_depth
        self.max_depth = max_depth
        self.depth_conv = nn.Conv2d(in_channels, 1, kernel_size=3, padding=1)

    def forward(self, features: torch.Tensor) -> HeadOutput:
        """(B, C, h, w) -> depth (B, 1, h, w), edges (B, 2) = range, uncertainty zeros."""
        depth = self.min_depth + (self.max_depth - self.min_depth) * torch.sigmoid(
            self.depth_conv(features)
        )
        edges = features.new_tensor([self.min_depth, self.max_depth]).expand(depth.shape[0], 2)
        return HeadOutput(depth, edges, torch.zeros_like(depth))

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """The direct regression (the zones are not used)."""
        return self(features)
