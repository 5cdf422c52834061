"""Depth as a learned, image-guided choice among the zones' readings: ``ZoneSelectHead``."""

from __future__ import annotations

import math

import torch
from torch import nn

from deltar.models.heads.base import DepthHead, HeadOutput, ZoneInputs
from deltar.models.heads.footprints import (
    footprint_pool,
    selection_outputs,
    softmax_over_zones,
    zone_gaussians,
)


class ZoneSelectHead(DepthHead):
    """Depth as a learned, image-guided choice among the zones' readings (in log depth).

    Each pixel takes a softmax-weighted geometric mean of the valid zones' means. The
    weights' logits are the zone prior's Gaussian log-weights (:func:`zone_gaussians`)
    plus a learned affinity between the pixel's features and each zone's features
    (pooled over the zone's Gaussian): a learned joint-bilateral interpolation, where
    the image says which zone's surface a pixel belongs to and the zones say how far it
    is. The output never leaves the range of the frame's valid readings, scales exactly
    with them, and the untrained head (zero affinity) is the zone prior itself.

    Args:
        in_channels: decoder feature width C.
        key_channels: width D of the pixel and zone embeddings.
        n_bins: number of entries of the reported ``bin_edges`` (N + 1 edges).
        min_depth, max_depth: output clamp, metres.
    """

    def __init__(self, in_channels: int, key_channels: int = 32, n_bins: int = 64,
                 min_depth: float = 1e-3, max_depth: float = 10.0) -> None:
        super().__init__()
        self.min_depth, self.max_depth = min_depth, max_depth
        self.scale = key_channels ** -0.5
        self.query = nn.Conv2d(in_channels, key_channels, kernel_size=1)
        self.key = nn.Linear(in_channels, key_channels)
        limit = math.log(3.0)
        self.register_buffer("edges", torch.linspace(-limit, limit, n_bins + 1),
                             persistent=False)
        # Zero affinity at the start: the untrained head returns the zone prior.
        nn.init.zeros_(self.query.weight)
        nn.init.zeros_(self.query.bias)

    def forward(self, features: torch.Tensor, zone_mean_m: torch.Tensor,
                zone_valid: torch.Tensor, zone_rects: torch.Tensor, stride: float
                ) -> HeadOutput:
        """Depth, bin edges and uncertainty.

        Args:
            features: (B, C, h, w) decoder features.
            zone_mean_m: (B, Z) zone means, metres (ignored where not valid).
            zone_valid: (B, Z) bool.
            zone_rects: (B, Z, 4) rectangles in pixels of the network input.
            stride: input pixels per feature cell.

        Returns:
            depth (B, 1, h, w) metres; bin_edges (B, N + 1) metres (log-spaced around the
            frame's typical depth); uncertainty (B, 1, h, w) metres: the depth times the
            spread of the chosen zones' log readings.
        """
        _, _, height, width = features.shape
        log_wy, log_wx = zone_gaussians(zone_rects, zone_valid, (height, width), stride,
                                        features.dtype)
        pooled = footprint_pool(features, log_wy, log_wx)  # (B, C, Z)
        keys = self.key(pooled.transpose(1, 2))  # (B, Z, D)
        queries = self.query(features).flatten(2).transpose(1, 2)  # (B, h*w, D)
        affinity = (queries @ keys.transpose(1, 2)) * self.scale  # (B, h*w, Z)
        # The prior's own logits: its softmax's per-pixel normaliser cancels in the
        # softmax below, so it is never computed (invalid zones are already at -1e4).
        prior_logits = (log_wy[:, :, None, :] + log_wx[:, None, :, :]).flatten(1, 2)
        logits = prior_logits + affinity
        valid = zone_valid.bool()
        weights = softmax_over_zones(logits)
        log_mean = torch.log(zone_mean_m.clamp_min(1e-3)).masked_fill(~valid, 0.0)
        log_depth = weights @ log_mean[..., None]  # (B, h*w, 1)
        spread = (weights @ (log_mean[..., None] ** 2) - log_depth ** 2).clamp_min(0.0).sqrt()
        return selection_outputs(log_depth, spread, valid, (height, width), self.edges,
                                 self.min_depth, self.max_depth)

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """The choice among the zones' means (:meth:`forward`)."""
        return self(features, zones.mean_m(features.dtype), zones.valid, zones.rects,
                    zones.stride)
