"""Per-pixel image descriptors from a frozen encoder, compared by cosine affinity.

The "descriptors" decoder of :class:`~deltar.models.network.DeltarNet`: no decoder to
train, the encoder's chosen scales resized, centred and normalised
(:class:`EncoderDescriptors`); the plane-select head
(:mod:`deltar.models.heads.plane_select`) compares them with the zones'.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

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
        #: Under ONNX export, return :class:`FactoredDescriptors` (set by the network
        #: when its head reads them; plain PyTorch never does).
        self.factored_export = False

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
            if self.factored_export:
                return self._factored(features, size)
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
        for part, weight, coarse in self._weighted_levels(features):
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


    def _weighted_levels(self, features: Sequence[torch.Tensor]
                         ) -> Iterator[tuple[torch.Tensor, torch.Tensor, tuple[int, int]]]:
        """For each encoder level read: its map (B, C, h, w), its channel weights (C,)
        and its (h, w) cells."""
        start = 0
        for level in self.levels:
            part = features[level]
            channels = int(part.shape[1])
            yield part, self.channel_weight[start:start + channels], (int(part.shape[-2]),
                                                                      int(part.shape[-1]))
            start += channels

    def _factored(self, features: Sequence[torch.Tensor], size: tuple[int, int]
                  ) -> FactoredDescriptors:
        """:meth:`forward`'s descriptors for the ONNX export, never formed: each scale as its
        coarse map (centred, weighted per channel), its constant bilinear matrices and a
        per-cell factor that holds both normalisations, which
        :class:`FactoredDescriptors` applies inside the products the head needs.

        The factors need each cell's squared norm of the upsampled map; a bilinear cell
        mixes at most 2 x 2 neighbouring coarse cells, so it is a sum over the coarse
        map's products with its right, lower and diagonal neighbours
        (:func:`_upsampled_square_norms`), all at the coarse size. Needs every channel
        weight non-zero (checked by the caller).
        """
        eps2 = 1e-24  # unit_channels' eps squared
        size = (int(size[0]), int(size[1]))
        parts, rows_all, cols_all, inverse_norms, weighted_sums = [], [], [], [], []
        for part, weight, coarse in self._weighted_levels(features):
            rows = bilinear_matrix(coarse[0], size[0])
            cols = bilinear_matrix(coarse[1], size[1])
            # The upsampled map's spatial mean, from the coarse cells each weighed by
            # its share of the upsampling (uniform for whole factors).
            share = np.outer(rows.sum(0, dtype=np.float64), cols.sum(0, dtype=np.float64))
            share = torch.from_numpy((share / share.sum()).astype(np.float32).reshape(-1, 1))
            part = part - torch.matmul(part.flatten(2), share)[..., None]  # one product
            part = part * weight[None, :, None, None]
            kernel = torch.stack([1.0 / (weight * weight), torch.ones_like(weight)])
            sums = _upsampled_square_norms(part, kernel, rows, cols)  # (B, 2, h, w)
            inverse = torch.rsqrt(sums[:, :1].clamp_min(eps2))  # 1 / |p|
            parts.append(part)
            rows_all.append(torch.from_numpy(rows))
            cols_all.append(torch.from_numpy(cols))
            inverse_norms.append(inverse)
            weighted_sums.append(sums[:, 1:] * inverse * inverse)
        total = torch.rsqrt(sum(weighted_sums).clamp_min(eps2))
        return FactoredDescriptors(parts, rows_all, cols_all,
                                   [inverse * total for inverse in inverse_norms])


class FactoredDescriptors:
    """Descriptors ``cat_k(factor_k * rows_k @ part_k @ cols_k^T)`` kept in factors (ONNX
    export): the two products the plane head needs are computed at the coarse sizes.

    Args:
        parts: per scale k, (B, C_k, h_k, w_k) coarse maps.
        rows, cols: per scale, (h, h_k) and (w, w_k) bilinear matrices.
        factors: per scale, (B, 1, h, w) per-cell factors.

    Attributes:
        shape: (B, C, h, w) of the descriptors they stand for; dtype likewise.
    """

    def __init__(self, parts: list[torch.Tensor], rows: list[torch.Tensor],
                 cols: list[torch.Tensor], factors: list[torch.Tensor]) -> None:
        self.parts, self.rows, self.cols, self.factors = parts, rows, cols, factors
        first = parts[0]
        self.shape = torch.Size((first.shape[0], sum(int(p.shape[1]) for p in parts),
                                 rows[0].shape[0], cols[0].shape[0]))
        self.dtype = first.dtype

    def pool(self, weights_y: torch.Tensor, weights_x: torch.Tensor) -> torch.Tensor:
        """(B, C, Z) sums over the cells of the descriptors times separable weights
        ``weights_y[:, i, z] * weights_x[:, j, z]`` ((B, h, Z) and (B, w, Z)): per scale
        ``part_k . (rows_k^T (factor_k * W_z) cols_k)`` (the weights brought to the coarse
        cells)."""
        batch = self.shape[0]
        footprint = weights_y.transpose(1, 2)[..., :, None] * \
            weights_x.transpose(1, 2)[..., None, :]  # (B, Z, h, w)
        pooled = []
        for part, rows, cols, factor in zip(self.parts, self.rows, self.cols, self.factors,
                                            strict=True):
            coarse = torch.matmul(rows.t(), torch.matmul(footprint * factor, cols))
            pooled.append(torch.matmul(part.reshape(batch, part.shape[1], -1),
                                       coarse.flatten(2).transpose(1, 2)))
        return torch.cat(pooled, dim=1)

    def dot(self, table: torch.Tensor) -> torch.Tensor:
        """(B, h, w, N) each cell's descriptor dotted with the columns of ``table``
        (B, C, N): per scale the coarse cells' products, upsampled, times the factor."""
        batch, height, width = self.shape[0], self.shape[2], self.shape[3]
        columns = table.shape[2]
        total, start = None, 0
        for part, rows, cols, factor in zip(self.parts, self.rows, self.cols, self.factors,
                                            strict=True):
            channels, coarse_h, coarse_w = (int(v) for v in part.shape[1:])
            coarse = torch.matmul(part.reshape(batch, channels, -1).transpose(1, 2),
                                  table[:, start:start + channels])  # (B, h_k*w_k, N)
            start += channels
            upsampled = torch.matmul(cols, coarse.reshape(batch, coarse_h, coarse_w, columns))
            upsampled = torch.matmul(rows, upsampled.reshape(batch, coarse_h, -1))
            term = upsampled.reshape(batch, height, width, columns) * \
                factor.reshape(batch, height, width, 1)
            total = term if total is None else total + term
        return total

    def materialise(self) -> torch.Tensor:
        """(B, C, h, w) the descriptors themselves."""
        return torch.cat([torch.matmul(rows, torch.matmul(part, cols.t())) * factor
                          for part, rows, cols, factor in zip(
                              self.parts, self.rows, self.cols, self.factors, strict=True)],
                         dim=1)


def _upsampled_square_norms(part: torch.Tensor, kernel: torch.Tensor, rows: np.ndarray,
                            cols: np.ndarray) -> torch.Tensor:
    """(B, K, h, w) per cell, ``sum_c kernel[k, c] * u[c]^2`` of the bilinear upsampling
    ``u = rows @ part @ cols^T`` of a (B, C, h_k, w_k) map, without forming ``u``.

    The map is upsampled along its rows' width only (``part @ cols^T``, h_k x w); each
    row of ``rows`` then weighs at most two neighbouring coarse rows
    (:func:`bilinear_matrix`), so ``u^2`` is ``rows^2`` times the squares plus twice
    ``rows[:, k] rows[:, k + 1]`` times the products of neighbouring rows, both summed
    over channels by ``kernel`` (K, C) at the coarse height.
    """
    coarse_h = int(part.shape[-2])
    wide = torch.matmul(part, torch.from_numpy(cols.T.copy()))  # (B, C, h_k, w)
    rows64 = rows.astype(np.float64)
    fine = torch.matmul(torch.from_numpy((rows64 * rows64).astype(np.float32)),
                        F.conv2d(wide * wide, kernel[:, :, None, None]))
    if coarse_h > 1:
        pairs = F.conv2d(wide[:, :, :-1] * wide[:, :, 1:], kernel[:, :, None, None])
        weights = 2.0 * rows64[:, :-1] * rows64[:, 1:]
        fine = fine + torch.matmul(torch.from_numpy(weights.astype(np.float32)), pairs)
    return fine


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
