"""The zones' footprints on a feature grid, shared by the zone-reading heads.

Each valid zone spreads over the feature grid as a separable Gaussian centred on the
zone (:func:`zone_gaussians`); heads pool features over it (:func:`footprint_pool`),
interpolate the zone means with it (:func:`zone_prior_map`) or choose among the zones
with it (:func:`selection_outputs`).
"""

from __future__ import annotations

import math

import torch

from deltar.models.heads.base import HeadOutput

#: Depth (metres) used where no zone of the frame is valid.
NO_ZONE_PRIOR_DEPTH = 2.0


def zone_gaussians(zone_rects: torch.Tensor, zone_valid: torch.Tensor,
                   size: tuple[int, int], stride: float, dtype: torch.dtype | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Separable Gaussian log-weights of every zone over a feature map.

    Each zone spreads with a Gaussian centred on the zone whose standard deviation is
    half the zone's size; invalid zones get a very negative (finite) weight.

    Args:
        zone_rects: (B, Z, 4) (y0, x0, y1, x1) in pixels of the network input.
        zone_valid: (B, Z) bool.
        size: (h, w) of the map.
        stride: input pixels per map cell.
        dtype: float dtype of the result (that of ``zone_rects`` when None).

    Returns:
        ``(log_wy, log_wx)``: (B, h, Z) and (B, w, Z) log-weights (zones last,
        contiguous); a cell's log-weight for zone z is ``log_wy[:, i, z] + log_wx[:, j, z]``.
    """
    rects = zone_rects.to(dtype or zone_rects.dtype) / stride
    centre_y = 0.5 * (rects[..., 0] + rects[..., 2]) - 0.5
    centre_x = 0.5 * (rects[..., 1] + rects[..., 3]) - 0.5
    sigma_y = (0.5 * (rects[..., 2] - rects[..., 0])).clamp_min(0.5)
    sigma_x = (0.5 * (rects[..., 3] - rects[..., 1])).clamp_min(0.5)
    rows = torch.arange(size[0], device=rects.device, dtype=rects.dtype)
    cols = torch.arange(size[1], device=rects.device, dtype=rects.dtype)
    log_wy = -0.5 * ((rows - centre_y[..., None]) / sigma_y[..., None]) ** 2  # (B, Z, h)
    log_wx = -0.5 * ((cols - centre_x[..., None]) / sigma_x[..., None]) ** 2  # (B, Z, w)
    log_wy = log_wy.masked_fill(~zone_valid.bool()[..., None], -1e4)
    # Zones on the last axis, contiguous: a softmax over the last axis exports to a fast
    # kernel, and in PyTorch a strided zone axis makes it slower.
    return log_wy.transpose(1, 2).contiguous(), log_wx.transpose(1, 2).contiguous()


def _axis_weights(log_weights: torch.Tensor) -> torch.Tensor:
    """(B, n, Z) log-weights along one axis -> weights summing to 1 over the axis.

    Log-weights more than 40 below a zone's largest are raised to it (a relative change
    of ~4e-18): their exponentials would be subnormal floats, which make CPU matrix
    products tens of times slower.
    """
    shifted = (log_weights - log_weights.amax(dim=1, keepdim=True)).clamp_min(-40.0)
    weights = torch.exp(shifted)
    return weights / weights.sum(dim=1, keepdim=True)


def footprint_pool(features: torch.Tensor, log_wy: torch.Tensor, log_wx: torch.Tensor
                   ) -> torch.Tensor:
    """Each zone's features: their average over the zone's Gaussian footprint.

    The footprint is separable, so it is normalised and applied one axis at a time and
    never formed as an (h, w, Z) tensor.

    Args:
        features: (B, C, h, w) feature map.
        log_wy, log_wx: (B, h, Z) and (B, w, Z) log-weights (:func:`zone_gaussians`).

    Returns:
        (B, C, Z) pooled features.
    """
    batch, channels, height, width = features.shape
    # Columns first as one matrix product, (B, C*h, w) @ (B, w, Z); then rows as a
    # product and sum: an einsum over (h) with Z shared by both operands runs as Z small
    # batched products with a copy each, 8x slower on CPU.
    per_row = features.reshape(batch, channels * height, width) @ _axis_weights(log_wx)
    per_row = per_row.reshape(batch, channels, height, -1)  # (B, C, h, Z)
    return (per_row * _axis_weights(log_wy)[:, None]).sum(dim=2)


def softmax_over_zones(logits: torch.Tensor) -> torch.Tensor:
    """Softmax over the last axis (zones) of (..., Z) logits, with weights below e^-80
    of the largest raised to it."""
    # Weights below e^-80 of a pixel's largest are raised to it (a change of ~1e-35):
    # exponentials that small are subnormal floats, which CPUs compute many times
    # slower.
    logits = (logits - logits.amax(dim=-1, keepdim=True)).clamp_min(-80.0)
    return torch.softmax(logits, dim=-1)


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
    standard deviation is half the zone's size (:func:`zone_gaussians`); a pixel's prior
    is the weighted geometric mean. Far from all zones the nearest zone dominates, so
    the prior extrapolates past the sensor's field of view instead of falling to zero.

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
    log_wy, log_wx = zone_gaussians(zone_rects, zone_valid, size, stride, zone_mean_m.dtype)
    weights = softmax_over_zones(log_wy[:, :, None, :] + log_wx[:, None, :, :])  # (B,h,w,Z)
    valid = zone_valid.bool()
    log_mean = torch.log(zone_mean_m.clamp_min(1e-3)).masked_fill(~valid, 0.0)
    log_prior = (weights.flatten(1, 2) @ log_mean[..., None]).reshape(
        log_mean.shape[0], 1, size[0], size[1])
    any_valid = valid.any(dim=1)[:, None, None, None]
    fallback = torch.full_like(log_prior, math.log(fallback_depth_m))
    return torch.exp(torch.where(any_valid, log_prior, fallback))


def selection_outputs(log_depth: torch.Tensor, spread: torch.Tensor, zone_valid: torch.Tensor,
                      size: tuple[int, int], log_edges: torch.Tensor,
                      min_depth: float | torch.Tensor, max_depth: float | torch.Tensor
                      ) -> HeadOutput:
    """The outputs of a zone-selecting head from its per-cell log depth and spread.

    Args:
        log_depth: (B, h*w, 1) chosen log depth (log metres).
        spread: (B, h*w, 1) standard deviation of the chosen log depths.
        zone_valid: (B, Z) bool; frames without a valid zone get
            :data:`NO_ZONE_PRIOR_DEPTH`.
        size: (h, w) of the map.
        log_edges: (N + 1,) log-ratio bin edges reported around the typical depth.
        min_depth, max_depth: output clamp, in the units of ``log_depth`` (metres, or
            per-frame (B,) tensors when the readings were divided by a frame scale).

    Returns:
        depth (B, 1, h, w) metres, bin_edges (B, N + 1) metres, uncertainty (B, 1, h, w)
        metres (depth times spread).
    """
    any_valid = zone_valid.any(dim=1)[:, None, None]
    log_depth = torch.where(any_valid, log_depth,
                            torch.full_like(log_depth, math.log(NO_ZONE_PRIOR_DEPTH)))
    batch = log_depth.shape[0]
    depth = torch.exp(log_depth).reshape(batch, 1, *size)
    if isinstance(min_depth, torch.Tensor) or isinstance(max_depth, torch.Tensor):
        low = torch.as_tensor(min_depth, dtype=depth.dtype).reshape(-1, 1, 1, 1)
        high = torch.as_tensor(max_depth, dtype=depth.dtype).reshape(-1, 1, 1, 1)
        depth = torch.minimum(torch.maximum(depth, low), high)
    else:
        depth = depth.clamp(min_depth, max_depth)
    uncertainty = depth * spread.reshape(batch, 1, *size)
    typical = torch.exp(log_depth.mean(dim=(1, 2)))[:, None]
    return HeadOutput(depth, typical * torch.exp(log_edges)[None], uncertainty)


def zone_geometry(rects: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Zone centres (B, Z) and the frame's mean zone height and width (B, 1), pixels."""
    centre_y = 0.5 * (rects[..., 0] + rects[..., 2])
    centre_x = 0.5 * (rects[..., 1] + rects[..., 3])
    zone_h = (rects[..., 2] - rects[..., 0]).mean(dim=1, keepdim=True).clamp_min(1e-6)
    zone_w = (rects[..., 3] - rects[..., 1]).mean(dim=1, keepdim=True).clamp_min(1e-6)
    return centre_y, centre_x, zone_h, zone_w


def zone_offsets(rects: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, k, j) offsets of zone j's centre from zone k's, in mean zone heights / widths."""
    centre_y, centre_x, zone_h, zone_w = zone_geometry(rects)
    return ((centre_y[:, None, :] - centre_y[:, :, None]) / zone_h[..., None],
            (centre_x[:, None, :] - centre_x[:, :, None]) / zone_w[..., None])
