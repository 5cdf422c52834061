"""Per-pixel image descriptors from a frozen encoder, compared by cosine affinity.

The "descriptors" decoder of :class:`~deltar.models.network.DeltarNet`: no decoder to
train, the encoder's chosen scales resized, centred and normalised
(:class:`EncoderDescriptors`); the plane-select head
(:mod:`deltar.models.heads.plane_select`) compares them with the zones'.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from deltar.models.decoder import DecoderZones
from deltar.models.encoders import FEATURE_STRIDES


def descriptor_levels(strides: Sequence[int]) -> int:
    """How many encoder maps, fine to coarse, descriptors at ``strides`` (pixels) read.

    Raises:
        ValueError: no stride, or one that is not among :data:`FEATURE_STRIDES`.
    """
    if not strides or any(s not in FEATURE_STRIDES for s in strides):
        raise ValueError(f"descriptor strides must be among {FEATURE_STRIDES}, got "
                         f"{tuple(strides)}")
    return max(FEATURE_STRIDES.index(s) for s in strides) + 1


class EncoderDescriptors(nn.Module):
    """Per-pixel image descriptors from chosen encoder scales, for cosine affinities.

    Each chosen feature map is resized (bilinear) to the output stride, centred by its
    per-image spatial mean (so that what all pixels share does not count as
    similarity) and L2-normalised over channels; the scales are concatenated, weighted
    per channel (learned, 1 at the start) and normalised again.

    Args:
        encoder_channels: channels of the encoder's maps, fine to coarse (strides 2, 4, ...).
        strides: which encoder strides to use (from :data:`FEATURE_STRIDES`).
        out_stride: input pixels per output cell.
    """

    def __init__(self, encoder_channels: Sequence[int], strides: Sequence[int] = (8, 16),
                 out_stride: int = 4) -> None:
        super().__init__()
        descriptor_levels(strides)  # checks them
        if out_stride not in FEATURE_STRIDES:
            raise ValueError(f"out_stride must be one of {FEATURE_STRIDES}, got {out_stride}")
        self.levels = tuple(FEATURE_STRIDES.index(s) for s in strides)
        self.out_stride = int(out_stride)
        self.channels = sum(int(encoder_channels[i]) for i in self.levels)
        self.channel_weight = nn.Parameter(torch.ones(self.channels))

    def forward(self, features: Sequence[torch.Tensor], zones: DecoderZones
                ) -> torch.Tensor:
        """Encoder maps (B, C_i, H / s_i, W / s_i) -> (B, C, H / out_stride, W / out_stride).

        Args:
            features: the encoder's maps, fine to coarse (up to the coarsest chosen
                stride at least).
            zones: the decoders' common second input; only ``image_size`` (H, W) of the
                network input, pixels, is read (the zones enter through the head).

        Returns:
            Unit-length descriptors per cell (over C = the chosen maps' channels).
        """
        height, width = zones.image_size
        size = (height // self.out_stride, width // self.out_stride)
        parts = []
        for level in self.levels:
            part = features[level]
            if tuple(part.shape[-2:]) != size:
                part = F.interpolate(part, size=size, mode="bilinear", align_corners=False)
            part = part - part.mean(dim=(2, 3), keepdim=True)
            parts.append(unit_channels(part))
        descriptors = torch.cat(parts, dim=1) * self.channel_weight[None, :, None, None]
        return unit_channels(descriptors)


def unit_channels(features: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``F.normalize(features, dim=1)`` from a sum of squares: on CPU the norm kernel is
    4x slower on (B, C, h, w) maps laid out channels-first. The clamp comes before the
    root, so an all-zero descriptor (a black frame) has a zero, not NaN, gradient."""
    squared = features * features
    if torch.onnx.is_in_onnx_export():
        # onnxruntime sums over the channels of an NCHW map several times slower than
        # it runs a 1x1 convolution with one output channel, which is the same sum.
        ones = torch.ones(1, int(squared.shape[1]), 1, 1, dtype=squared.dtype)
        squares = F.conv2d(squared, ones)
    else:
        squares = squared.sum(dim=1, keepdim=True)
    return features * torch.rsqrt(squares.clamp_min(eps * eps))
