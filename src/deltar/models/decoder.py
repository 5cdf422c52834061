"""U-Net style decoder with zone fusion at the 1/16, 1/8 and 1/4 scales."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from deltar.models.fusion import ZoneImageFusion
from deltar.models.zone_patches import ZonePatchResampler

#: Strides of the three fused decoder scales, coarse to fine.
FUSION_STRIDES = (16, 8, 4)


class DecoderZones(NamedTuple):
    """What every decoder takes besides the encoder's maps (each reads what it needs).

    Attributes:
        image_size: (H, W) of the network input, pixels.
        features: distribution features for strides 16, 8, 4, (B, Z, K, C_i) each;
            None without a distribution encoder.
        valid: (B, Z) bool zone validity; None without fusion.
        resamplers: zone patch resamplers for strides 16, 8, 4; None without fusion.
    """

    image_size: tuple[int, int]
    features: Sequence[torch.Tensor] | None = None
    valid: torch.Tensor | None = None
    resamplers: Sequence[ZonePatchResampler] | None = None


class UpBlock(nn.Module):
    """Upsample to the skip map, concatenate it, then two (3x3 conv, BN, LeakyReLU).

    Args:
        in_channels: channels of the upsampled input plus the skip map.
        out_channels: output channels.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1),
            nn.BatchNorm2d(out_channels), nn.LeakyReLU(),
            nn.Conv2d(out_channels, out_channels, kernel_size=3, padding=1),
            nn.BatchNorm2d(out_channels), nn.LeakyReLU(),
        )

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) and skip (B, C_s, H, W) -> (B, out_channels, H, W)."""
        up = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=True)
        return self.block(torch.cat([up, skip], dim=1))


class FusionDecoder(nn.Module):
    """Decoder from five encoder maps (strides 2..32) to a stride-2 feature map.

    At strides 16, 8 and 4 the upsampled features are reduced to half width by a 1x1
    convolution, fused with the zone features by :class:`ZoneImageFusion`, and the
    fused half is concatenated back (``[reduced, fused]``). Without fusion (the
    five-channel ablation) the upsampled features pass straight on.

    Args:
        encoder_channels: channels of the encoder maps, strides 2, 4, 8, 16, 32.
        decoder_channels: five widths: bottleneck, then after each up block.
        out_channels: width of the stride-2 output map.
        fusion_kwargs: keyword arguments for every :class:`ZoneImageFusion`
            (``num_hypotheses``, ``layer_order``, ``mode``, heads), or None for no fusion.
        design_size: (H, W) input size the positional encodings are laid out for.
    """

    def __init__(
        self,
        encoder_channels: Sequence[int],
        decoder_channels: Sequence[int] = (256, 256, 128, 64, 32),
        out_channels: int = 128,
        fusion_kwargs: dict | None = None,
        design_size: tuple[int, int] = (480, 640),
    ) -> None:
        super().__init__()
        if len(encoder_channels) != 5 or len(decoder_channels) != 5:
            raise ValueError("encoder_channels and decoder_channels need five entries each")
        enc = list(encoder_channels)[::-1]  # strides 32, 16, 8, 4, 2
        dec = list(decoder_channels)
        self.bottleneck = nn.Conv2d(enc[0], dec[0], kernel_size=1)
        self.up_blocks = nn.ModuleList(
            UpBlock(dec[i] + enc[i + 1], dec[i + 1]) for i in range(4)
        )
        self.fusion_dims = tuple(dec[i + 1] // 2 for i in range(3))
        self.uses_fusion = fusion_kwargs is not None
        if self.uses_fusion:
            self.reduce = nn.ModuleList(
                nn.Conv2d(dec[i + 1], self.fusion_dims[i], kernel_size=1) for i in range(3)
            )
            self.fusions = nn.ModuleList(
                ZoneImageFusion(
                    self.fusion_dims[i],
                    (design_size[0] // stride, design_size[1] // stride),
                    **fusion_kwargs,
                )
                for i, stride in enumerate(FUSION_STRIDES)
            )
        self.out_conv = nn.Conv2d(dec[4], out_channels, kernel_size=3, padding=1)

    def forward(self, image_features: Sequence[torch.Tensor], zones: DecoderZones
                ) -> torch.Tensor:
        """Decode.

        Args:
            image_features: five maps (B, C_i, H / s, W / s), s = 2, 4, 8, 16, 32.
            zones: the zones' distribution features (``fusion_dims[i]`` channels at
                strides 16, 8, 4), validity and resamplers; unused without fusion.

        Returns:
            (B, out_channels, H / 2, W / 2) features.
        """
        skips = list(image_features)[::-1]
        x = self.bottleneck(skips[0])
        for i, up_block in enumerate(self.up_blocks):
            x = up_block(x, skips[i + 1])
            if i < 3 and self.uses_fusion:
                reduced = self.reduce[i](x)
                fused = self.fusions[i](reduced, zones.features[i], zones.valid,
                                        zones.resamplers[i])
                x = torch.cat([reduced, fused], dim=1)
        return self.out_conv(x)
