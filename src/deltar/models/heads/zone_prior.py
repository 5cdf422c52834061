"""A depth head that refines a smooth prior interpolated from the zone means.

An untrained network with this head already returns the zone prior (a smooth
interpolation of the valid zones' means), so training only has to learn the
correction: per pixel, a softmax over N fixed bins of the log-ratio between the depth
and the prior. This makes small models trained on little data (CPU budgets) start from
the sensor's own reading rather than from a constant.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from deltar.models.heads.base import DepthHead, HeadOutput, ZoneInputs, softmax_moments
from deltar.models.heads.footprints import zone_prior_map


class ZonePriorHead(DepthHead):
    """Per-pixel softmax over N log-ratio bins around the zone prior.

    Args:
        in_channels: decoder feature width.
        n_bins: number of log-ratio bins N.
        hidden_channels: width of the hidden 3x3 convolution.
        max_ratio: the bins span depth / prior in [1 / max_ratio, max_ratio].
        min_depth: smallest output depth, metres.
        max_depth: largest output depth, metres.
    """

    def __init__(self, in_channels: int, n_bins: int, hidden_channels: int,
                 max_ratio: float = 3.0, min_depth: float = 1e-3,
                 max_depth: float = 10.0) -> None:
        super().__init__()
        if max_ratio <= 1.0:
            raise ValueError(f"max_ratio must be > 1, got {max_ratio}")
        self.min_depth = min_depth
        self.max_depth = max_depth
        limit = math.log(max_ratio)
        self.register_buffer("edges", torch.linspace(-limit, limit, n_bins + 1),
                             persistent=False)
        self.hidden = nn.Sequential(
            nn.Conv2d(in_channels + 1, hidden_channels, kernel_size=3, padding=1),
            nn.LeakyReLU(),
        )
        self.logits_conv = nn.Conv2d(hidden_channels, n_bins, kernel_size=1)
        # Zero logits: a uniform, symmetric distribution, so the untrained head
        # returns the prior itself.
        nn.init.zeros_(self.logits_conv.weight)
        nn.init.zeros_(self.logits_conv.bias)

    def forward(self, features: torch.Tensor, prior_m: torch.Tensor) -> HeadOutput:
        """Depth, bin edges and uncertainty.

        Args:
            features: (B, C, h, w) decoder features.
            prior_m: (B, 1, h, w) zone prior in metres (:func:`zone_prior_map`).

        Returns:
            depth (B, 1, h, w) metres; bin_edges (B, N + 1) metres, the log-ratio bins
            placed at each image's geometric-mean prior; uncertainty (B, 1, h, w)
            metres (standard deviation of the per-pixel distribution, to first order).
        """
        log_prior = torch.log(prior_m)
        centred = log_prior - log_prior.mean(dim=(2, 3), keepdim=True)
        logits = self.logits_conv(self.hidden(torch.cat([features, centred], dim=1)))
        centres = 0.5 * (self.edges[:-1] + self.edges[1:])
        log_ratio, spread = softmax_moments(logits, centres)
        depth = (prior_m * torch.exp(log_ratio)).clamp(self.min_depth, self.max_depth)
        typical = torch.exp(log_prior.mean(dim=(1, 2, 3)))[:, None]
        edges = typical * torch.exp(self.edges)[None]
        return HeadOutput(depth, edges, depth * spread)

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """The refinement (:meth:`forward`) of the zone prior (:func:`zone_prior_map`)."""
        prior = zone_prior_map(zones.mean_m(features.dtype), zones.valid, zones.rects,
                               tuple(features.shape[-2:]), zones.stride)
        return self(features, prior)
