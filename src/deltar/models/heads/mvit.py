"""The paper's head: AdaBins' mini-ViT refinement over adaptive bins."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from deltar.models.heads.bins import BinsPredict, bin_width_regressor, normalise_bin_widths


class MiniViTHead(BinsPredict):
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
        self.width_regressor = bin_width_regressor(embedding_dim, n_bins)
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
