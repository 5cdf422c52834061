"""The release's head: adaptive bins (a global bin-width regressor and a per-pixel softmax).

A bins head predicts, per image, N normalised bin widths over ``[min_depth,
max_depth]`` and, per pixel, logits of a softmax over the N bins; depth is the
expectation of the bin centres and the uncertainty is the standard deviation of that
per-pixel distribution (both in metres).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from deltar.models.heads.base import DepthHead, HeadOutput, ZoneInputs, bins_to_depth


def bin_width_regressor(embedding_dim: int, n_bins: int) -> nn.Sequential:
    """The release's regressor of N raw bin widths from an (B, E) image embedding."""
    return nn.Sequential(nn.Linear(embedding_dim, 256), nn.LeakyReLU(), nn.Linear(256, 256),
                         nn.LeakyReLU(), nn.Linear(256, n_bins))


def normalise_bin_widths(raw: torch.Tensor) -> torch.Tensor:
    """(B, N) raw regressor output -> (B, N) positive widths summing to 1.

    The release's normalisation: ``relu(raw) + 0.1``, then divide by the sum.
    """
    widths = torch.relu(raw) + 0.1
    return widths / widths.sum(dim=1, keepdim=True)


class BinsPredict(DepthHead):
    """``predict`` of the bins heads: widths and logits from ``forward``, then the bins."""

    min_depth: float
    max_depth: float

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """The :class:`HeadOutput` (metres) from the bins' widths over
        ``[min_depth, max_depth]`` and each pixel's weights over the bins (``zones``
        unused)."""
        widths, logits = self(features)
        return HeadOutput(*bins_to_depth(widths, logits, self.min_depth, self.max_depth))


class BinsHead(BinsPredict):
    """The release's head: global bin-width regressor plus a per-pixel bin softmax.

    Args:
        in_channels: input feature width.
        n_bins: number of depth bins N.
        embedding_dim: width of the range-attention features.
        min_depth: depth of the first bin edge, metres.
        max_depth: depth of the last bin edge, metres.
    """

    def __init__(
        self, in_channels: int, n_bins: int = 256, embedding_dim: int = 128,
        min_depth: float = 1e-3, max_depth: float = 10.0,
    ) -> None:
        super().__init__()
        self.min_depth, self.max_depth = min_depth, max_depth
        self.range_conv = nn.Conv2d(in_channels, embedding_dim, kernel_size=3, padding=1)
        self.global_conv = nn.Conv2d(in_channels, embedding_dim, kernel_size=1, bias=False)
        self.width_regressor = bin_width_regressor(embedding_dim, n_bins)
        self.logits_conv = nn.Conv2d(embedding_dim, n_bins, kernel_size=1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, h, w) -> normalised widths (B, N) and bin logits (B, N, h, w)."""
        # mean(conv1x1(x)) == conv1x1(mean(x)) for a bias-free 1x1 convolution; the
        # right-hand side skips a full-resolution convolution.
        pooled = F.linear(features.mean(dim=(2, 3)), self.global_conv.weight.flatten(1))
        widths = normalise_bin_widths(self.width_regressor(pooled))
        return widths, self.logits_conv(self.range_conv(features))
