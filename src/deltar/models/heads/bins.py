"""Depth heads: the one head interface, adaptive bins (release head and AdaBins mViT)
and a direct regressor.

Every head is a :class:`DepthHead`: ``head.predict(features, zones)`` takes the
decoder's features and the frame's :class:`ZoneInputs` and returns a
:class:`HeadOutput` (depth, bin edges, uncertainty in metres), so
:class:`~deltar.models.network.DeltarNet` calls every head the same way. Each head's
``forward`` keeps its own, narrower inputs (what the head itself computes on).

A bins head predicts, per image, N normalised bin widths over ``[min_depth,
max_depth]`` and, per pixel, logits of a softmax over the N bins; depth is the expectation of
the bin centres and the uncertainty is the standard deviation of that per-pixel
distribution (both in metres).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn


def normalise_bin_widths(raw: torch.Tensor) -> torch.Tensor:
    """(B, N) raw regressor output -> (B, N) positive widths summing to 1.

    The release's normalisation: ``relu(raw) + 0.1``, then divide by the sum.
    """
    widths = torch.relu(raw) + 0.1
    return widths / widths.sum(dim=1, keepdim=True)


def bins_to_depth(
    normalised_widths: torch.Tensor,
    logits: torch.Tensor,
    min_depth: float,
    max_depth: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Depth, bin edges and uncertainty from bin widths and per-pixel bin logits.

    The per-pixel bin probabilities are ``softmax(logits, dim=1)``; depth is their
    expectation over the bin centres and the uncertainty their standard deviation.

    Args:
        normalised_widths: (B, N) widths summing to 1.
        logits: (B, N, h, w) per-pixel bin logits. Overwritten in place when
            autograd is off (it is a temporary of the head).
        min_depth: depth of the first edge, metres.
        max_depth: depth of the last edge, metres.

    Returns:
        depth (B, 1, h, w) metres, bin_edges (B, N + 1) metres, and uncertainty
        (B, 1, h, w) metres.
    """
    widths = (max_depth - min_depth) * normalised_widths
    widths = F.pad(widths, (1, 0), mode="constant", value=min_depth)
    edges = torch.cumsum(widths, dim=1)
    centres = 0.5 * (edges[:, :-1] + edges[:, 1:])  # (B, N)
    depth, spread = softmax_moments(logits, centres)
    return depth, edges, spread


def softmax_moments(logits: torch.Tensor, centres: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard deviation of per-pixel softmax distributions over bin centres.

    Computed as three moments with one matrix product over the bins (no softmax
    along the channel axis, which exporters lower to slow transposes).

    Args:
        logits: (B, N, h, w) per-pixel bin logits. Overwritten in place when autograd
            is off (it is a temporary of the head).
        centres: (B, N) or (N,) bin centres, in the unit of the result (metres or
            log-ratio).

    Returns:
        mean (B, 1, h, w) and standard deviation (B, 1, h, w) of the centres under
        ``softmax(logits, dim=1)``.
    """
    batch, bins, height, width = logits.shape
    centres = centres.expand(batch, bins)
    # Unnormalised softmax weights; the normaliser is the zeroth moment below.
    peak = logits.amax(dim=1, keepdim=True)
    if torch.is_grad_enabled():
        weights = torch.exp(logits - peak)
    else:
        weights = logits.sub_(peak).exp_()
    # Moments about a per-image reference keep E[c^2] - E[c]^2 well conditioned.
    reference = centres.mean(dim=1, keepdim=True)
    shifted = centres - reference
    moments = torch.stack([torch.ones_like(shifted), shifted, shifted**2], dim=1)  # (B, 3, N)
    if weights.is_contiguous():
        totals = (moments @ weights.reshape(batch, bins, height * width)).reshape(
            batch, 3, height, width
        )
    else:
        # Channels-last logits (from channels-last convolutions): the bins are the
        # fastest axis, so (h w, N) @ (N, 3) reads them without a layout copy.
        by_pixel = weights.permute(0, 2, 3, 1).reshape(batch, height * width, bins)
        totals = (by_pixel @ moments.transpose(1, 2)).transpose(1, 2).reshape(
            batch, 3, height, width
        )
    mean_shift = totals[:, 1:2] / totals[:, 0:1]
    variance = totals[:, 2:3] / totals[:, 0:1] - mean_shift**2
    return mean_shift + reference[:, :, None, None], variance.clamp_min(0).sqrt()


class HeadOutput(NamedTuple):
    """What every head returns (unpacks as ``depth, bin_edges, uncertainty``).

    Attributes:
        depth: (B, 1, h, w) metres, in the decoder's output grid.
        bin_edges: (B, N + 1) metres (a head without bins reports its depth range).
        uncertainty: (B, 1, h, w) metres, the per-pixel standard deviation.
    """

    depth: torch.Tensor
    bin_edges: torch.Tensor
    uncertainty: torch.Tensor


@dataclass(frozen=True)
class ZoneInputs:
    """The frame's zones as every head receives them (heads read what they need).

    Attributes:
        hypotheses: (B, Z, K) depth hypotheses per zone, metres (as the network sees
            them: divided by the frame's scale with ``zone_scale_norm``).
        valid: (B, Z) bool.
        rects: (B, Z, 4) (y0, x0, y1, x1) zone rectangles in network-input pixels.
        stride: network-input pixels per feature cell of the head's input.
        mean_sigma: optional (B, Z, 2) zone mean and sigma, metres; when None the zone
            mean is the hypotheses' mean.
        no_target: optional (B, Z) bool, zones that reported *no target* (nothing within
            the sensor's range); heads that do not use it ignore it.
        scale_m: optional (B,) metres per unit of ``hypotheses`` and ``mean_sigma`` (the
            frame's scale with ``zone_scale_norm``; None: they are in metres).
    """

    hypotheses: torch.Tensor
    valid: torch.Tensor
    rects: torch.Tensor
    stride: float
    mean_sigma: torch.Tensor | None = None
    no_target: torch.Tensor | None = None
    scale_m: torch.Tensor | None = None

    def mean_m(self, dtype: torch.dtype) -> torch.Tensor:
        """(B, Z) zone means in metres, as ``dtype``."""
        mean = self.mean_sigma[..., 0] if self.mean_sigma is not None else \
            self.hypotheses.mean(dim=2)
        return mean.to(dtype)


class DepthHead(nn.Module):
    """The interface of every depth head: :meth:`predict`.

    Subclasses implement ``predict`` (and ``forward``, the head's own computation);
    ``traceable`` is set by :meth:`deltar.models.DeltarNet.set_traceable` for export.
    """

    traceable: bool = False
    #: Whether :meth:`predict` reads ``ZoneInputs.no_target`` (an export then takes it).
    uses_no_target: bool = False

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """Depth, bin edges and uncertainty from decoder features.

        Args:
            features: (B, C, h, w) decoder features.
            zones: the frame's zones (:class:`ZoneInputs`).

        Returns:
            The :class:`HeadOutput`, in metres, on the ``h x w`` grid.
        """
        raise NotImplementedError


class _BinsPredict(DepthHead):
    """``predict`` of the bins heads: widths and logits from ``forward``, then the bins."""

    min_depth: float
    max_depth: float

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        widths, logits = self(features)
        return HeadOutput(*bins_to_depth(widths, logits, self.min_depth, self.max_depth))


class BinsHead(_BinsPredict):
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
        self.width_regressor = nn.Sequential(
            nn.Linear(embedding_dim, 256),
            nn.LeakyReLU(),
            nn.Linear(256, 256),
            nn.LeakyReLU(),
            nn.Linear(256, n_bins),
        )
        self.logits_conv = nn.Conv2d(embedding_dim, n_bins, kernel_size=1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, h, w) -> normalised widths (B, N) and bin logits (B, N, h, w)."""
        # mean(conv1x1(x)) == conv1x1(mean(x)) for a bias-free 1x1 convolution; the
        # right-hand side skips a full-resolution convolution.
        pooled = F.linear(features.mean(dim=(2, 3)), self.global_conv.weight.flatten(1))
        widths = normalise_bin_widths(self.width_regressor(pooled))
        return widths, self.logits_conv(self.range_conv(features))


class MiniViTHead(_BinsPredict):
    """AdaBins' mini-ViT refinement (the paper's head).

    Patch embeddings of the decoder output go through a transformer encoder together
    with 1 + Q learned query tokens. The first query regresses the bin widths; the
    other Q are dotted with per-pixel features to give Q range-attention maps,
    which a 1x1 convolution turns into a softmax over the N bins. (AdaBins takes
    its queries from the first output patch tokens; learned query tokens give the
    same computation for any input size, even one with fewer than Q + 1 patches.)

    Args:
        in_channels: input feature width.
        n_bins: number of depth bins N.
        embedding_dim: transformer width E.
        num_queries: Q range-attention queries.
        patch_size: side of the patch embedding in cells.
        num_layers: transformer layers.
        num_heads: transformer heads.
        design_tokens: (rows, cols) of the learned patch-position grid.
        min_depth: depth of the first bin edge, metres.
        max_depth: depth of the last bin edge, metres.

    With ``traceable`` set (export), the transformer runs without PyTorch's fused
    encoder kernel, which has no ONNX equivalent (the plain path computes the same).
    """

    def __init__(
        self,
        in_channels: int,
        n_bins: int = 256,
        embedding_dim: int = 128,
        num_queries: int = 128,
        patch_size: int = 16,
        num_layers: int = 4,
        num_heads: int = 4,
        design_tokens: tuple[int, int] = (15, 20),
        min_depth: float = 1e-3,
        max_depth: float = 10.0,
    ) -> None:
        super().__init__()
        self.min_depth, self.max_depth = min_depth, max_depth
        self.patch_size = patch_size
        self.patch_embed = nn.Conv2d(
            in_channels, embedding_dim, kernel_size=patch_size, stride=patch_size
        )
        self.patch_position = nn.Parameter(torch.empty(embedding_dim, *design_tokens))
        self.queries = nn.Parameter(torch.empty(1 + num_queries, embedding_dim))
        nn.init.trunc_normal_(self.patch_position, std=0.2)
        nn.init.trunc_normal_(self.queries, std=0.2)
        layer = nn.TransformerEncoderLayer(
            embedding_dim, num_heads, dim_feedforward=1024, dropout=0.0, batch_first=True
        )
        self.transformer = nn.TransformerEncoder(layer, num_layers, enable_nested_tensor=False)
        self.pixel_conv = nn.Conv2d(in_channels, embedding_dim, kernel_size=3, padding=1)
        self.width_regressor = nn.Sequential(
            nn.Linear(embedding_dim, 256),
            nn.LeakyReLU(),
            nn.Linear(256, 256),
            nn.LeakyReLU(),
            nn.Linear(256, n_bins),
        )
        self.logits_conv = nn.Conv2d(num_queries, n_bins, kernel_size=1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, h, w) -> normalised widths (B, N) and bin logits (B, N, h, w)."""
        batch = features.shape[0]
        patches = self.patch_embed(features)
        position = F.interpolate(
            self.patch_position[None], size=patches.shape[-2:], mode="bilinear",
            align_corners=True,
        )
        tokens = rearrange(patches + position, "b e h w -> b (h w) e")
        queries = self.queries[None].expand(batch, -1, -1)
        with _plain_transformer() if self.traceable else contextlib.nullcontext():
            out = self.transformer(torch.cat([queries, tokens], dim=1))
        widths = normalise_bin_widths(self.width_regressor(out[:, 0]))
        range_queries = out[:, 1 : self.queries.shape[0]]
        range_maps = torch.einsum("behw,bqe->bqhw", self.pixel_conv(features), range_queries)
        return widths, self.logits_conv(range_maps)


@contextlib.contextmanager
def _plain_transformer() -> Iterator[None]:
    """Run transformer layers on their plain (traceable) path while tracing."""
    fastpath = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)
    try:
        yield
    finally:
        torch.backends.mha.set_fastpath_enabled(fastpath)


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
