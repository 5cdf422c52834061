"""Fusion of image features with zone distribution features at one decoder scale."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from deltar.models.attention import ImageSelfAttention, LinearAttentionLayer
from deltar.models.zone_patches import ZonePatchResampler

#: How zone features reach the image at a fusion scale.
FUSION_MODES = ("attention", "whole_image", "additive", "concat")
#: Layer kinds that may appear in ``layer_order``.
LAYER_KINDS = ("hist2image", "image")


class ZoneImageFusion(nn.Module):
    """Alternating zone-to-image cross attention and image self attention.

    With ``mode="attention"`` (the release): learned positional encodings are added
    to image tokens and to the K hypothesis tokens; each "hist2image" layer lets the
    tokens of every zone's resampled feature patch attend to that zone's hypothesis
    features, zeroes invalid zones, resamples the patches back and adds them to the
    image tokens; each "image" layer is Twins-style self attention over the map.
    Each "hist2image" layer reads the positionally encoded input map plus the zone
    updates made before the first "image" layer (as the release computes it), not
    the output of the previous image layer.

    Ablation modes: ``"whole_image"`` (no patch-distribution correspondence: every
    image token attends to the hypotheses of all valid zones), ``"additive"`` (no
    image-to-distribution attention: each zone's max-pooled distribution feature is
    projected and added to its patch), ``"concat"`` (no attention fusion: the pooled
    zone features are painted into a map, concatenated with the image features and
    mixed by a 1x1 convolution; "image" layers still run).

    Args:
        dim: feature width C of the image map and of the distribution features.
        design_map_size: (H, W) of this map at the design input size (480x640 in the
            release); sets the positional-encoding grid and the attention window.
        num_hypotheses: K, the length of the hypothesis positional encoding.
        layer_order: sequence of "hist2image" / "image".
        mode: one of :data:`FUSION_MODES`.
        cross_heads: heads of the zone-to-image attention (4 in the release).
        self_heads: heads of the image self attention (8 in the release).
    """

    def __init__(
        self,
        dim: int,
        design_map_size: tuple[int, int],
        num_hypotheses: int,
        layer_order: Sequence[str] = ("hist2image", "image", "hist2image", "image"),
        mode: str = "attention",
        cross_heads: int = 4,
        self_heads: int = 8,
    ) -> None:
        super().__init__()
        if mode not in FUSION_MODES:
            raise ValueError(f"fusion mode must be one of {FUSION_MODES}, got {mode!r}")
        unknown = [kind for kind in layer_order if kind not in LAYER_KINDS]
        if unknown:
            raise ValueError(f"layer_order entries must be in {LAYER_KINDS}, got {unknown}")
        self.mode = mode
        self.layer_order = tuple(layer_order)
        height, width = design_map_size
        self.image_position = nn.Parameter(torch.empty(height, width, dim))
        self.hypothesis_position = nn.Parameter(torch.empty(num_hypotheses, dim))
        nn.init.trunc_normal_(self.image_position, std=0.2)
        nn.init.trunc_normal_(self.hypothesis_position, std=0.2)
        # Window side: about the fourth root of the token count (12, 9, 6 at 1/4, 1/8,
        # 1/16 of 480x640), fixed by the design size so weights transfer across inputs.
        window = math.ceil(math.sqrt(math.sqrt(height * width)))
        layers: list[nn.Module] = []
        for kind in self.layer_order:
            if kind == "image":
                layers.append(ImageSelfAttention(dim, self_heads, window))
            elif mode in ("attention", "whole_image"):
                layers.append(LinearAttentionLayer(dim, cross_heads))
            elif mode == "additive":
                layers.append(nn.Linear(dim, dim))
            else:
                layers.append(nn.Identity())
        self.layers = nn.ModuleList(layers)
        self.concat_mix = nn.Conv2d(2 * dim, dim, kernel_size=1) if mode == "concat" else None

    def _image_position(self, height: int, width: int) -> torch.Tensor:
        """Positional encoding (C, H, W) for a map of the given size."""
        grid = self.image_position
        design_h, design_w = grid.shape[:2]
        if (height, width) == (design_h, design_w):
            return grid.permute(2, 0, 1)
        if height <= design_h and width <= design_w:
            # A crop of the design grid, as in the release: random while training
            # (it trained on random crops), centred at inference for determinism.
            if self.training:
                top = int(torch.randint(0, design_h - height + 1, (1,)))
                left = int(torch.randint(0, design_w - width + 1, (1,)))
            else:
                top, left = (design_h - height) // 2, (design_w - width) // 2
            return grid[top : top + height, left : left + width].permute(2, 0, 1)
        resized = F.interpolate(
            grid.permute(2, 0, 1)[None], size=(height, width), mode="bilinear", align_corners=True
        )
        return resized[0]

    def _hypothesis_position(self, count: int) -> torch.Tensor:
        """Positional encoding (K, C) for K hypothesis tokens."""
        position = self.hypothesis_position
        if position.shape[0] == count:
            return position
        resized = F.interpolate(
            position.T[None], size=count, mode="linear", align_corners=True
        )
        return resized[0].T

    def forward(
        self,
        image_features: torch.Tensor,
        zone_features: torch.Tensor,
        zone_valid: torch.Tensor,
        resampler: ZonePatchResampler,
    ) -> torch.Tensor:
        """Fuse zone features into the image map.

        Args:
            image_features: (B, C, H, W) image features.
            zone_features: (B, Z, K, C) per-hypothesis distribution features.
            zone_valid: (B, Z) bool; invalid zones contribute nothing.
            resampler: zone patch resampler for this map.

        Returns:
            (B, C, H, W) fused features.
        """
        batch, _, height, width = image_features.shape
        embedded = image_features + self._image_position(height, width)
        hypotheses = zone_features + self._hypothesis_position(zone_features.shape[2])
        valid = zone_valid.to(embedded.dtype)
        if self.mode == "concat":
            embedded = self.concat_mix(
                torch.cat([embedded, self._paint_pooled(hypotheses, valid, resampler)], dim=1)
            )
        tokens = rearrange(embedded, "b c h w -> b (h w) c")
        # The map cross attention reads. In the release the token tensor is a view of
        # this map until the first image layer replaces it, so zone updates made
        # before then also land in what later cross-attention layers read.
        source_map = embedded
        tokens_alias_source = True
        for kind, layer in zip(self.layer_order, self.layers, strict=True):
            if kind == "image":
                tokens = layer(tokens, (height, width))
                tokens_alias_source = False
                continue
            if self.mode == "concat":
                continue
            if self.mode == "whole_image":
                source = rearrange(hypotheses, "b z k c -> b (z k) c")
                source_mask = zone_valid[:, :, None].expand(hypotheses.shape[:3]).flatten(1)
                tokens = layer(tokens, source, source_mask)
                continue
            patches = resampler.gather(source_map)
            per_zone = rearrange(hypotheses, "b z k c -> (b z) k c")
            if self.mode == "attention":
                fused = layer(patches, per_zone)
            else:
                fused = patches + layer(per_zone.amax(dim=1))[:, None, :]
            fused = fused * valid.reshape(-1, 1, 1)
            added = resampler.scatter(fused, batch)
            tokens = tokens + rearrange(added, "b c h w -> b (h w) c")
            if tokens_alias_source:
                source_map = source_map + added
        return rearrange(tokens, "b (h w) c -> b c h w", h=height)

    @staticmethod
    def _paint_pooled(
        hypotheses: torch.Tensor, valid: torch.Tensor, resampler: ZonePatchResampler
    ) -> torch.Tensor:
        """(B, C, H, W) map holding each valid zone's max-pooled feature over its patch."""
        batch, zones, _, channels = hypotheses.shape
        pooled = hypotheses.amax(dim=2) * valid[..., None]
        p_h, p_w = resampler.window.patch
        patches = pooled.reshape(batch * zones, 1, channels).expand(-1, p_h * p_w, -1)
        return resampler.scatter(patches, batch)
