"""Per-pixel image descriptors from a frozen encoder, compared by cosine affinity.

The "descriptors" decoder of :class:`~deltar.models.network.DeltarNet`: no decoder to
train, the encoder's chosen scales resized, centred and normalised
(:class:`EncoderDescriptors`); the plane-select head
(:mod:`deltar.models.heads.plane_select`) compares them with the zones'.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
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
        if torch.onnx.is_in_onnx_export() and bool((self.channel_weight != 0).all()):
            return self._export_forward(features, size)
        parts = []
        for level in self.levels:
            part = features[level]
            if tuple(part.shape[-2:]) != size:
                part = F.interpolate(part, size=size, mode="bilinear", align_corners=False)
            part = part - part.mean(dim=(2, 3), keepdim=True)
            parts.append(unit_channels(part))
        descriptors = torch.cat(parts, dim=1) * self.channel_weight[None, :, None, None]
        return unit_channels(descriptors)

    def _export_forward(self, features: Sequence[torch.Tensor], size: tuple[int, int]
                        ) -> torch.Tensor:
        """:meth:`forward`'s descriptors as the ONNX export writes them: the same values
        (to float32 rounding) in fewer passes over the (B, C, h, w) maps, which onnxruntime
        runs one operator at a time.

        - A map upsampled by whole factors is centred before it is resized (bilinear
          upsampling by a whole factor, ``align_corners=False``, weighs every source cell
          alike, so the spatial mean is kept) and weighted per channel there too (the two
          commute), on 1/4 or 1/16 of the cells.
        - The resize is two matrix products with constant interpolation matrices
          (:func:`bilinear_matrix`), several times faster in onnxruntime than ``Resize``.
        - Both normalisations come from one 1x1 convolution per scale over the weighted
          map's squares, with two output channels: ``|p|^2`` (weights ``1 / w^2``) and
          ``|w p|^2``; the per-cell factors are then computed on (B, 1, h, w) maps and
          each scale is multiplied once.

        Needs every channel weight non-zero (checked by the caller).
        """
        eps2 = 1e-24  # unit_channels' eps squared
        size = (int(size[0]), int(size[1]))  # fixed by the export
        scaled, inverse_norms, weighted_sums = [], [], []
        start = 0
        for level in self.levels:
            part = features[level]
            channels = int(part.shape[1])
            weight = self.channel_weight[start:start + channels]
            start += channels
            coarse = (int(part.shape[-2]), int(part.shape[-1]))
            whole = size[0] % coarse[0] == 0 and size[1] % coarse[1] == 0
            if whole:
                part = part - part.mean(dim=(2, 3), keepdim=True)
            part = part * weight[None, :, None, None]
            if coarse != size:
                rows = torch.from_numpy(bilinear_matrix(coarse[0], size[0]))
                cols = torch.from_numpy(bilinear_matrix(coarse[1], size[1]).T.copy())
                part = torch.matmul(rows, torch.matmul(part, cols))
            if not whole:
                part = part - part.mean(dim=(2, 3), keepdim=True)
            kernel = torch.stack([1.0 / (weight * weight), torch.ones_like(weight)])
            sums = F.conv2d(part * part, kernel[:, :, None, None])  # (B, 2, h, w)
            inverse = torch.rsqrt(sums[:, :1].clamp_min(eps2))  # 1 / |p|
            scaled.append(part)
            inverse_norms.append(inverse)
            weighted_sums.append(sums[:, 1:] * inverse * inverse)  # |w p / |p||^2
        total = torch.rsqrt(sum(weighted_sums).clamp_min(eps2))
        return torch.cat([part * (inverse * total)
                          for part, inverse in zip(scaled, inverse_norms, strict=True)], dim=1)


def bilinear_matrix(size_in: int, size_out: int) -> np.ndarray:
    """(size_out, size_in) float32 matrix of 1-D linear resizing as ``F.interpolate`` does it
    (``align_corners=False``, source index clamped at 0): output = matrix @ input.

    Args:
        size_in, size_out: lengths in cells (>= 1).
    """
    scale = size_in / size_out
    source = np.maximum((np.arange(size_out) + 0.5) * scale - 0.5, 0.0)
    low = np.minimum(np.floor(source).astype(int), size_in - 1)
    high = np.minimum(low + 1, size_in - 1)
    fraction = source - low
    matrix = np.zeros((size_out, size_in), dtype=np.float64)
    np.add.at(matrix, (np.arange(size_out), low), 1.0 - fraction)
    np.add.at(matrix, (np.arange(size_out), high), fraction)
    return matrix.astype(np.float32)


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
