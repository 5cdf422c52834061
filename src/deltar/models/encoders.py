"""Encoders: a timm image backbone and the stacked-PointNet distribution encoder."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

#: Strides (input pixels per cell) of the five feature maps the decoder expects.
FEATURE_STRIDES = (2, 4, 8, 16, 32)


class ImageEncoder(nn.Module):
    """Multi-scale image features from any timm backbone with ``features_only`` support.

    The backbone is built with random weights (``pretrained=False``): weights come
    from a checkpoint, never from a download inside the constructor.

    Args:
        backbone: timm model name, e.g. ``"tf_efficientnetv2_b3"``.
        in_channels: input channels (3 for RGB, 5 for RGB + zone mean/sigma maps).
        stem_activation: apply the activation after the stem batch norm. The released
            DELTAR encoder was built with timm 0.5.4, where the stem activation was a
            separate module it did not include; timm >= 0.9 fuses it into ``bn1``,
            so ``False`` removes it to reproduce the release.
        levels: how many maps to return, fine to coarse (strides 2 .. 2^levels); a
            decoder that reads only the finer ones asks for fewer. The backbone's layers
            past the last returned map are not built (timm drops them for most
            backbones; the blocks of an EfficientNet-style one are cut here); their
            tensors in a state dict saved with the whole backbone are skipped on
            loading, any other unexpected or missing tensor still fails a strict load.
    """

    def __init__(self, backbone: str, in_channels: int = 3, stem_activation: bool = True,
                 levels: int = len(FEATURE_STRIDES)) -> None:
        super().__init__()
        import timm

        if isinstance(levels, bool) or not isinstance(levels, int) or \
                not 1 <= levels <= len(FEATURE_STRIDES):
            raise ValueError(f"levels must be an integer in 1..{len(FEATURE_STRIDES)}, got "
                             f"{levels!r}")
        self.backbone = timm.create_model(
            backbone, pretrained=False, features_only=True, in_chans=in_channels,
            out_indices=tuple(range(levels)),
        )
        reductions = tuple(self.backbone.feature_info.reduction())
        if reductions != FEATURE_STRIDES[:levels]:
            raise ValueError(
                f"backbone {backbone!r} gives feature strides {reductions}; "
                f"the decoder needs {FEATURE_STRIDES[:levels]}"
            )
        self.channels: tuple[int, ...] = tuple(self.backbone.feature_info.channels())
        blocks = getattr(self.backbone, "blocks", None)
        #: Blocks per stage of the whole backbone (EfficientNet-style ones; None for
        #: others): the layout that converting flat-numbered pretrained weights needs.
        self.full_stage_lengths: tuple[int, ...] | None = (
            tuple(len(stage) for stage in blocks) if isinstance(blocks, nn.Sequential)
            else None)
        self._unused_keys: frozenset[str] = frozenset()
        if levels < len(FEATURE_STRIDES):
            built = set(self.backbone.state_dict())
            if self._drop_unused_blocks():
                whole = built  # timm built every block; the cut removed the unused ones
            else:  # timm left the unused layers out itself: their names need a whole build
                whole = set(timm.create_model(backbone, pretrained=False, features_only=True,
                                              in_chans=in_channels).state_dict())
            self._unused_keys = frozenset(
                f"backbone.{key}" for key in whole - set(self.backbone.state_dict()))
        if not stem_activation:
            stem_norm = getattr(self.backbone, "bn1", None)
            if stem_norm is None or not hasattr(stem_norm, "act"):
                raise ValueError(f"backbone {backbone!r} has no stem norm-activation to remove")
            stem_norm.act = nn.Identity()

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        """(B, C_in, H, W) image -> ``levels`` maps (B, C_i, H / s_i, W / s_i), s_i = 2, 4, ..."""
        return self.backbone(image)

    def _drop_unused_blocks(self) -> bool:
        """Cut an EfficientNet-style block list after the last returned map.

        timm's features-only EfficientNets run every block whatever maps are asked
        for; the blocks after the last one returned cost time (the bundled encoder's
        stride-32 stages: over a third of its time at 256x320) and change nothing.

        Returns:
            Whether the backbone is EfficientNet-style (its blocks are cut here, if any
            follow the last returned map).
        """
        blocks = getattr(self.backbone, "blocks", None)
        last = self.backbone.feature_info.module_name()[-1]
        if not isinstance(blocks, nn.Sequential) or not last.startswith("blocks."):
            return False
        keep = int(last.split(".")[1]) + 1
        if keep < len(blocks):
            self.backbone.blocks = blocks[:keep]
        return True

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # Weights saved with the whole backbone (every checkpoint before the cut) still
        # load strictly: only the tensors of the layers not built are skipped.
        for key in [k for k in state_dict
                    if k.startswith(prefix) and k[len(prefix):] in self._unused_keys]:
            del state_dict[key]
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class PointNetBlock(nn.Module):
    """Shared per-point MLP: three (1x1 conv, batch norm, ReLU) layers, no pooling.

    Args:
        in_channels: feature width of each input point.
        out_channels: feature width of each output point.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = in_channels
        for _ in range(3):
            layers += [nn.Conv1d(width, out_channels, 1), nn.BatchNorm1d(out_channels), nn.ReLU()]
            width = out_channels
        self.mlp = nn.Sequential(*layers)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(N, C_in, K) points -> (N, C_out, K) point features."""
        return self.mlp(points)


class DistributionEncoder(nn.Module):
    """Stacked PointNets (without T-Net) over each zone's set of depth hypotheses.

    Every hypothesis is a point; each block maps every point independently (no
    pooling, no down-sampling), so the output keeps one token per hypothesis.

    Args:
        point_dim: values per point (1 for a depth hypothesis in metres, 2 for a
            zone's (mean, sigma) in metres in the mean/variance ablation).
        widths: output width of each block; block i feeds decoder fusion level i.
    """

    def __init__(self, point_dim: int = 1, widths: Sequence[int] = (32, 64, 128)) -> None:
        super().__init__()
        in_widths = [point_dim, *widths[:-1]]
        self.blocks = nn.ModuleList(
            PointNetBlock(c_in, c_out) for c_in, c_out in zip(in_widths, widths, strict=True)
        )
        self.widths = tuple(widths)

    def forward(self, points: torch.Tensor) -> list[torch.Tensor]:
        """(B, Z, K, point_dim) points in metres -> list of (B, Z, K, width_i) features."""
        batch, zones, count, dim = points.shape
        x = points.reshape(batch * zones, count, dim).transpose(1, 2)
        features = []
        for block in self.blocks:
            x = block(x)
            features.append(x.transpose(1, 2).reshape(batch, zones, count, -1))
        return features
