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

from deltar.models.heads import softmax_moments

#: Depth (metres) used where no zone of the frame is valid.
NO_ZONE_PRIOR_DEPTH = 2.0


def zone_prior_map(
    zone_mean_m: torch.Tensor,
    zone_valid: torch.Tensor,
    zone_rects: torch.Tensor,
    size: tuple[int, int],
    stride: float,
    fallback_depth_m: float = NO_ZONE_PRIOR_DEPTH,
) -> torch.Tensor:
    """Smooth depth map interpolated from zone means (Gaussian-weighted, in log depth).

    Every valid zone spreads its mean with a Gaussian centred on the zone whose
    standard deviation is half the zone's size; a pixel's prior is the weighted
    geometric mean. Far from all zones the nearest zone dominates, so the prior
    extrapolates past the sensor's field of view instead of falling to zero.

    Args:
        zone_mean_m: (B, Z) zone means in metres (ignored where not valid).
        zone_valid: (B, Z) bool.
        zone_rects: (B, Z, 4) (y0, x0, y1, x1) in pixels of the network input.
        size: (h, w) of the output map.
        stride: input pixels per output pixel.
        fallback_depth_m: prior of frames without any valid zone, metres.

    Returns:
        (B, 1, h, w) prior depth in metres.
    """
    rects = zone_rects.to(zone_mean_m.dtype) / stride
    centre_y = 0.5 * (rects[..., 0] + rects[..., 2]) - 0.5
    centre_x = 0.5 * (rects[..., 1] + rects[..., 3]) - 0.5
    sigma_y = (0.5 * (rects[..., 2] - rects[..., 0])).clamp_min(0.5)
    sigma_x = (0.5 * (rects[..., 3] - rects[..., 1])).clamp_min(0.5)
    rows = torch.arange(size[0], device=rects.device, dtype=rects.dtype)
    cols = torch.arange(size[1], device=rects.device, dtype=rects.dtype)
    log_wy = -0.5 * ((rows - centre_y[..., None]) / sigma_y[..., None]) ** 2  # (B, Z, h)
    log_wx = -0.5 * ((cols - centre_x[..., None]) / sigma_x[..., None]) ** 2  # (B, Z, w)
    valid = zone_valid.bool()
    # Invalid zones get a very negative (finite) log-weight so softmax stays NaN-free.
    log_wy = log_wy.masked_fill(~valid[..., None], -1e4)
    # Zones on the last axis, contiguous: a softmax over the last axis exports to a fast
    # kernel, and in PyTorch a strided zone axis makes it slower.
    log_wy = log_wy.transpose(1, 2).contiguous()  # (B, h, Z)
    log_wx = log_wx.transpose(1, 2).contiguous()  # (B, w, Z)
    logits = log_wy[:, :, None, :] + log_wx[:, None, :, :]  # (B, h, w, Z)
    # Weights below e^-80 of a pixel's largest are raised to it (a change of ~1e-35):
    # exponentials that small are subnormal floats, which CPUs compute many times
    # slower (most of this map's time, before).
    logits = (logits - logits.amax(dim=-1, keepdim=True)).clamp_min(-80.0)
    weights = torch.softmax(logits, dim=-1)  # (B, h, w, Z)
    log_mean = torch.log(zone_mean_m.clamp_min(1e-3)).masked_fill(~valid, 0.0)
    log_prior = (weights.flatten(1, 2) @ log_mean[..., None]).reshape(
        log_mean.shape[0], 1, size[0], size[1])
    any_valid = valid.any(dim=1)[:, None, None, None]
    fallback = torch.full_like(log_prior, math.log(fallback_depth_m))
    return torch.exp(torch.where(any_valid, log_prior, fallback))


class ZonePriorHead(nn.Module):
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

    def forward(self, features: torch.Tensor, prior_m: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
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
        return depth, edges, depth * spread
