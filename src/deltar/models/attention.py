"""Linear-attention transformer layers used to fuse zone and image features.

The attention is the kernelised "linear" attention of Katharopoulos et al. (2020),
``softmax(Q K^T) V`` replaced by ``phi(Q) (phi(K)^T V)`` with ``phi(x) = elu(x) + 1``,
so the cost is linear in the number of tokens. Image self-attention follows Twins
(Chu et al., 2021): attention inside local windows, then attention to a spatially
sub-sampled summary of the whole map.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn


def elu_feature_map(x: torch.Tensor) -> torch.Tensor:
    """The positive feature map ``phi(x) = elu(x) + 1`` of linear attention (any shape).

    Computed exactly as the release does, ``elu`` then ``+ 1`` in the input's precision:
    in float32 it is exactly 0 below about x = -17, where ``exp(x)`` is not, and with
    queries that negative the two forms move depth by millimetres.
    """
    return F.elu(x) + 1.0


def linear_attention(
    query_features: torch.Tensor,
    key_features: torch.Tensor,
    values: torch.Tensor,
    key_mask: torch.Tensor | None = None,
    eps: float = 1e-6,
) -> torch.Tensor:
    """Multi-head linear attention on feature-mapped queries and keys.

    Args:
        query_features: (N, heads, L, D) ``elu_feature_map`` of the projected queries.
        key_features: (N, heads, S, D) ``elu_feature_map`` of the projected keys.
        values: (N, heads, S, Dv) projected values.
        key_mask: optional (N, S) bool; False keys are ignored.
        eps: added to the normaliser so that it never divides by zero.

    Returns:
        (N, heads, L, Dv) attended values.
    """
    q, k = query_features, key_features
    if key_mask is not None:
        keep = key_mask[:, None, :, None].to(k.dtype)
        k = k * keep
        values = values * keep
    num_keys = values.shape[2]
    # Scaling the values by 1 / S before the key-value product (and back after) keeps
    # the sums in range in half precision; in float32 it only changes rounding.
    key_value = k.transpose(2, 3) @ (values / num_keys)  # (N, heads, D, Dv)
    normaliser = 1.0 / (q @ k.sum(dim=2, keepdim=True).transpose(2, 3) + eps)  # (N, heads, L, 1)
    return (q @ key_value) * (normaliser * num_keys)


class LinearAttentionLayer(nn.Module):
    """One transformer layer: linear attention from ``x`` to ``source``, then a feed-forward.

    ``out = x + norm2(ffn([x, norm1(attention(x, source))]))`` (the LoFTR layer layout).
    Used for cross attention (zone patch -> depth hypotheses) and, with
    ``source = x``, for self attention.

    Args:
        dim: token width C.
        num_heads: attention heads; ``dim`` must be divisible by it.
    """

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        if dim % num_heads != 0:
            raise ValueError(f"dim ({dim}) must be divisible by num_heads ({num_heads})")
        self.num_heads = num_heads
        self.query_proj = nn.Linear(dim, dim, bias=False)
        self.key_proj = nn.Linear(dim, dim, bias=False)
        self.value_proj = nn.Linear(dim, dim, bias=False)
        self.out_proj = nn.Linear(dim, dim, bias=False)
        self.ffn = nn.Sequential(
            nn.Linear(2 * dim, 2 * dim, bias=False),
            nn.ReLU(inplace=True),
            nn.Linear(2 * dim, dim, bias=False),
        )
        self.norm_message = nn.LayerNorm(dim)
        self.norm_out = nn.LayerNorm(dim)

    def forward(
        self, x: torch.Tensor, source: torch.Tensor, source_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Attend from ``x`` (N, L, C) to ``source`` (N, S, C); returns (N, L, C).

        ``source_mask`` (N, S) bool, optional, hides False source tokens.
        """
        heads = self.num_heads
        # The feature map runs before the head split, on contiguous memory (much faster).
        q = rearrange(elu_feature_map(self.query_proj(x)), "n l (h d) -> n h l d", h=heads)
        k = rearrange(elu_feature_map(self.key_proj(source)), "n s (h d) -> n h s d", h=heads)
        v = rearrange(self.value_proj(source), "n s (h d) -> n h s d", h=heads)
        message = rearrange(linear_attention(q, k, v, source_mask), "n h l d -> n l (h d)")
        message = self.norm_message(self.out_proj(message))
        message = self.norm_out(self.ffn(torch.cat([x, message], dim=2)))
        return x + message


class LocallyGroupedSelfAttention(nn.Module):
    """Self attention inside non-overlapping ``window x window`` windows.

    The map is zero-padded on the right and bottom to a multiple of the window; the
    padded tokens take part in the attention (as in the release), then are cropped.

    Args:
        dim: token width C.
        num_heads: attention heads.
        window: window side in feature cells.
    """

    def __init__(self, dim: int, num_heads: int, window: int) -> None:
        super().__init__()
        self.window = window
        self.layer = LinearAttentionLayer(dim, num_heads)

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """``x`` (B, H*W, C) tokens of an (H, W) map; returns the same shape."""
        height, width = size
        ws = self.window
        grid = rearrange(x, "b (h w) c -> b h w c", h=height, w=width)
        pad_bottom = (ws - height % ws) % ws
        pad_right = (ws - width % ws) % ws
        grid = F.pad(grid, (0, 0, 0, pad_right, 0, pad_bottom))
        rows, cols = grid.shape[1] // ws, grid.shape[2] // ws
        windows = rearrange(grid, "b (r i) (c j) d -> (b r c) (i j) d", i=ws, j=ws)
        windows = self.layer(windows, windows)
        grid = rearrange(windows, "(b r c) (i j) d -> b (r i) (c j) d", r=rows, c=cols, i=ws)
        return rearrange(grid[:, :height, :width], "b h w c -> b (h w) c")


class GlobalSubsampledAttention(nn.Module):
    """Attention from every token to a strided-convolution summary of the whole map.

    Args:
        dim: token width C.
        num_heads: attention heads.
        reduction: kernel and stride of the summarising convolution (cells).
    """

    def __init__(self, dim: int, num_heads: int, reduction: int) -> None:
        super().__init__()
        self.layer = LinearAttentionLayer(dim, num_heads)
        if reduction > 1:
            self.reduce = nn.Conv2d(dim, dim, kernel_size=reduction, stride=reduction)
            self.reduce_norm = nn.LayerNorm(dim)
        else:
            self.reduce = None
            self.reduce_norm = None

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """``x`` (B, H*W, C) tokens of an (H, W) map; returns the same shape."""
        summary = x
        if self.reduce is not None:
            grid = rearrange(x, "b (h w) c -> b c h w", h=size[0], w=size[1])
            # A map smaller than the kernel would give no summary token at all.
            pad_h = max(0, self.reduce.kernel_size[0] - size[0])
            pad_w = max(0, self.reduce.kernel_size[1] - size[1])
            if pad_h or pad_w:
                grid = F.pad(grid, (0, pad_w, 0, pad_h))
            summary = self.reduce_norm(rearrange(self.reduce(grid), "b c h w -> b (h w) c"))
        return self.layer(x, summary)


class ImageSelfAttention(nn.Module):
    """Twins-style image self attention: local windows, then global sub-sampled attention.

    Args:
        dim: token width C.
        num_heads: attention heads (the release uses 8).
        window: local window side and global reduction factor (cells).
    """

    def __init__(self, dim: int, num_heads: int, window: int) -> None:
        super().__init__()
        self.local = LocallyGroupedSelfAttention(dim, num_heads, window)
        self.global_ = GlobalSubsampledAttention(dim, num_heads, window)

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """``x`` (B, H*W, C) tokens of an (H, W) map; returns the same shape."""
        return self.global_(self.local(x, size), size)
