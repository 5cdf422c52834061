"""U-Net style decoder with zone fusion at the 1/16, 1/8 and 1/4 scales."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from deltar.models.fusion import ZoneImageFusion
from deltar.models.zone_patches import ZonePatchResampler

#: Strides of the three fused decoder scales, coarse to fine.
FUSION_STRIDES = (16, 8, 4)


#: Convolution units of the decoder's up blocks.
DECODER_BLOCKS = ("conv", "separable")


def conv_unit(in_channels: int, out_channels: int, block: str = "conv") -> list[nn.Module]:
    """One decoder unit: a 3x3 convolution (or its separable form), BN, LeakyReLU.

    Args:
        in_channels: input channels.
        out_channels: output channels.
        block: "conv" (a full 3x3 convolution) or "separable" (a depthwise 3x3 then a
            pointwise 1x1 convolution: about ``9 / out_channels + 1 / 9`` of the FLOPs).

    Returns:
        The modules, in order (the batch norm follows a convolution, so it folds).
    """
    if block == "conv":
        convs = [nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1)]
    elif block == "separable":
        convs = [nn.Conv2d(in_channels, in_channels, kernel_size=3, padding=1,
                           groups=in_channels, bias=False),
                 nn.Conv2d(in_channels, out_channels, kernel_size=1)]
    else:
        raise ValueError(f"decoder block must be one of {DECODER_BLOCKS}, got {block!r}")
    return [*convs, nn.BatchNorm2d(out_channels), nn.LeakyReLU()]


class UpBlock(nn.Module):
    """Upsample to the skip map, concatenate it, then ``convs`` x (3x3 conv, BN, LeakyReLU).

    Args:
        in_channels: channels of the upsampled input plus the skip map.
        out_channels: output channels.
        block: "conv" or "separable" (see :func:`conv_unit`).
        convs: number of units (2 in the release).
    """

    def __init__(self, in_channels: int, out_channels: int, block: str = "conv",
                 convs: int = 2) -> None:
        super().__init__()
        if convs < 1:
            raise ValueError(f"an up block needs at least one convolution, got {convs}")
        units = conv_unit(in_channels, out_channels, block)
        for _ in range(convs - 1):
            units += conv_unit(out_channels, out_channels, block)
        self.block = nn.Sequential(*units)

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
        block: unit of the up blocks, "conv" (release) or "separable" (see
            :func:`conv_unit`).
        convs: units per up block, coarse to fine (strides 16, 8, 4, 2); (2, 2, 2, 2) in
            the release.
        out_kernel: kernel size of the output convolution at stride 2 (3 or 1).
    """

    def __init__(
        self,
        encoder_channels: Sequence[int],
        decoder_channels: Sequence[int] = (256, 256, 128, 64, 32),
        out_channels: int = 128,
        fusion_kwargs: dict | None = None,
        design_size: tuple[int, int] = (480, 640),
        block: str = "conv",
        convs: Sequence[int] = (2, 2, 2, 2),
        out_kernel: int = 3,
    ) -> None:
        super().__init__()
        if len(encoder_channels) != 5 or len(decoder_channels) != 5:
            raise ValueError("encoder_channels and decoder_channels need five entries each")
        if len(convs) != 4:
            raise ValueError(f"convs needs one count per up block (four), got {tuple(convs)}")
        if out_kernel not in (1, 3):
            raise ValueError(f"out_kernel must be 1 or 3, got {out_kernel}")
        enc = list(encoder_channels)[::-1]  # strides 32, 16, 8, 4, 2
        dec = list(decoder_channels)
        self.bottleneck = nn.Conv2d(enc[0], dec[0], kernel_size=1)
        self.up_blocks = nn.ModuleList(
            UpBlock(dec[i] + enc[i + 1], dec[i + 1], block, convs[i]) for i in range(4)
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
        self.out_conv = nn.Conv2d(dec[4], out_channels, kernel_size=out_kernel,
                                  padding=out_kernel // 2)

    def forward(
        self,
        image_features: Sequence[torch.Tensor],
        zone_features: Sequence[torch.Tensor] | None,
        zone_valid: torch.Tensor | None,
        resamplers: Sequence[ZonePatchResampler] | None,
    ) -> torch.Tensor:
        """Decode.

        Args:
            image_features: five maps (B, C_i, H / s, W / s), s = 2, 4, 8, 16, 32.
            zone_features: distribution features for strides 16, 8, 4:
                (B, Z, K, fusion_dims[i]) each; None without fusion.
            zone_valid: (B, Z) bool; None without fusion.
            resamplers: zone patch resamplers for strides 16, 8, 4; None without fusion.

        Returns:
            (B, out_channels, H / 2, W / 2) features.
        """
        skips = list(image_features)[::-1]
        x = self.bottleneck(skips[0])
        for i, up_block in enumerate(self.up_blocks):
            x = up_block(x, skips[i + 1])
            if i < 3 and self.uses_fusion:
                reduced = self.reduce[i](x)
                fused = self.fusions[i](reduced, zone_features[i], zone_valid, resamplers[i])
                x = torch.cat([reduced, fused], dim=1)
        return self.out_conv(x)
