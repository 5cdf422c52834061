"""DeltarNet: dense metric depth from an RGB image and multi-zone ToF distributions.

The network is built from its parts' configs (:mod:`deltar.models.config`): the image
encoder, a decoder named in :data:`DECODERS` and a head named in :data:`HEADS`, each
registry entry built with the same call.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from deltar.contract import SIZE_DIVISOR
from deltar.models.affinity import EncoderDescriptors, descriptor_levels
from deltar.models.config import (
    DECODER_CONFIGS,
    HEAD_CONFIGS,
    OUTPUT_STAGE_OPTIONS,
    DecoderConfig,
    EncoderConfig,
    FusionConfig,
    HeadConfig,
    InputConfig,
    NetworkConfig,
    OutputConfig,
)
from deltar.models.decoder import FUSION_STRIDES, DecoderZones, FusionDecoder
from deltar.models.encoders import FEATURE_STRIDES, DistributionEncoder, ImageEncoder
from deltar.models.heads.base import DepthHead, ZoneInputs
from deltar.models.heads.bins import BinsHead
from deltar.models.heads.direct import DirectDepthHead
from deltar.models.heads.mvit import MiniViTHead
from deltar.models.heads.plane_select import PlanarSelectHead
from deltar.models.heads.zone_prior import ZonePriorHead
from deltar.models.heads.zone_select import ZoneSelectHead
from deltar.models.zone_patches import ZonePatchResampler, zone_window

#: A head builder: (width of the features it reads, the network's config) -> the head.
HeadBuilder = Callable[[int, NetworkConfig], DepthHead]


def _bins_head(width: int, c: NetworkConfig) -> DepthHead:
    return BinsHead(width, c.head.n_bins, width, min_depth=c.output.min_depth,
                    max_depth=c.output.max_depth)


def _mvit_head(width: int, c: NetworkConfig) -> DepthHead:
    height, wide = c.inputs.design_size
    return MiniViTHead(width, c.head.n_bins, width, min_depth=c.output.min_depth,
                       max_depth=c.output.max_depth, design_tokens=(height // 32, wide // 32))


def _direct_head(width: int, c: NetworkConfig) -> DepthHead:
    return DirectDepthHead(width, c.output.min_depth, c.output.max_depth)


def _zone_prior_head(width: int, c: NetworkConfig) -> DepthHead:
    return ZonePriorHead(width, c.head.n_bins, width, min_depth=c.output.min_depth,
                         max_depth=c.output.max_depth)


def _zone_select_head(width: int, c: NetworkConfig) -> DepthHead:
    return ZoneSelectHead(width, width, c.head.n_bins, min_depth=c.output.min_depth,
                          max_depth=c.output.max_depth)


def _plane_select_head(width: int, c: NetworkConfig) -> DepthHead:
    # Compares the descriptors as they come: no layer to size by the width.
    return PlanarSelectHead(c.head.temperature, c.head.planar, n_bins=c.head.n_bins,
                            min_depth=c.output.min_depth, max_depth=c.output.max_depth,
                            no_target_depth=c.output.no_target_depth)


#: Each head by its config's ``name`` (:data:`deltar.models.config.HEAD_CONFIGS`), one
#: file each under :mod:`deltar.models.heads`.
HEADS: dict[str, HeadBuilder] = {
    "bins": _bins_head,
    "mvit": _mvit_head,
    "direct": _direct_head,
    "zone_prior": _zone_prior_head,
    "zone_select": _zone_select_head,
    "plane_select": _plane_select_head,
}
assert tuple(HEADS) == tuple(HEAD_CONFIGS)


class BuiltDecoder(NamedTuple):
    """What a decoder builder returns.

    Attributes:
        decoder: the module called as ``decoder(image_features, DecoderZones)``.
        distribution_encoder: the zone distributions' encoder it fuses, or None.
        out_channels: width of the features it gives the head.
    """

    decoder: nn.Module
    distribution_encoder: DistributionEncoder | None
    out_channels: int


class DecoderEntry(NamedTuple):
    """A decoder of the registry: how many encoder maps it reads, and its builder.

    Attributes:
        encoder_levels: (decoder config) -> number of encoder maps, fine to coarse.
        build: (encoder map widths fine to coarse, the network's config) -> decoder.
    """

    encoder_levels: Callable[[Any], int]
    build: Callable[[Sequence[int], NetworkConfig], BuiltDecoder]


def _fusion_decoder(encoder_channels: Sequence[int], c: NetworkConfig) -> BuiltDecoder:
    """The zone-fusion decoder and the distribution encoder it fuses."""
    d = c.decoder
    five_channel = c.encoder.image_input == "rgb_zone_maps"
    mean_sigma_points = d.distribution_input == "mean_sigma"
    fusion_kwargs = None
    if not five_channel:
        fusion_kwargs = {"num_hypotheses": 1 if mean_sigma_points else c.inputs.num_hypotheses,
                         "layer_order": d.fusion_layers, "mode": d.fusion,
                         "cross_heads": d.cross_heads, "self_heads": d.self_heads}
    decoder = FusionDecoder(encoder_channels, d.channels, d.out_channels, fusion_kwargs,
                            c.inputs.design_size)
    if five_channel:
        return BuiltDecoder(decoder, None, d.out_channels)
    distribution = DistributionEncoder(point_dim=2 if mean_sigma_points else 1,
                                       widths=decoder.fusion_dims[::-1])
    return BuiltDecoder(decoder, distribution, d.out_channels)


def _descriptor_decoder(encoder_channels: Sequence[int], c: NetworkConfig) -> BuiltDecoder:
    """Frozen-encoder descriptors at stride 4 (no decoder to train)."""
    decoder = EncoderDescriptors(encoder_channels, c.decoder.strides)
    return BuiltDecoder(decoder, None, decoder.channels)


#: Each decoder by its config's ``name`` (:data:`deltar.models.config.DECODER_CONFIGS`).
DECODERS: dict[str, DecoderEntry] = {
    "fusion": DecoderEntry(lambda d: len(FEATURE_STRIDES), _fusion_decoder),
    # Reads the encoder up to its coarsest chosen stride only.
    "descriptors": DecoderEntry(lambda d: descriptor_levels(d.strides),
                                _descriptor_decoder),
}
assert tuple(DECODERS) == tuple(DECODER_CONFIGS)


class DeltarNet(nn.Module):
    """The DELTAR network (Li et al., ECCV 2022), built from its parts' configs.

    Every argument is a frozen dataclass of :mod:`deltar.models.config` (see there for
    each option); a part left out takes its defaults (the release's architecture).
    :func:`~deltar.models.presets.create_model` builds the named presets;
    :meth:`from_config` / :meth:`config` round-trip the stored form.

    Args:
        encoder: the image encoder (:class:`~deltar.models.config.EncoderConfig`).
        decoder: the decoder of :data:`DECODERS` and its options
            (:class:`~deltar.models.config.FusionConfig` or
            :class:`~deltar.models.config.DescriptorConfig`).
        head: the depth head of :data:`HEADS` and its options
            (:class:`~deltar.models.config.HeadConfig`, or
            :class:`~deltar.models.config.PlaneSelectConfig` for "plane_select").
        inputs: the input contract (:class:`~deltar.models.config.InputConfig`).
        output: depth range and output contract
            (:class:`~deltar.models.config.OutputConfig`).

    Raises:
        ValueError: parts that do not fit together (naming the option).
    """

    def __init__(
        self,
        encoder: EncoderConfig | None = None,
        decoder: DecoderConfig | None = None,
        head: HeadConfig | None = None,
        inputs: InputConfig | None = None,
        output: OutputConfig | None = None,
    ) -> None:
        super().__init__()
        spec = NetworkConfig(inputs or InputConfig(), encoder or EncoderConfig(),
                             decoder or FusionConfig(), head or HeadConfig(),
                             output or OutputConfig())
        #: The parts' configs (frozen); :meth:`config` is its stored form.
        self.network_config = spec
        self.zone_scale_norm = spec.inputs.zone_scale_norm
        self.min_depth = spec.output.min_depth
        self.max_depth = spec.output.max_depth
        self.five_channel = spec.encoder.image_input == "rgb_zone_maps"
        self.mean_sigma_points = (isinstance(spec.decoder, FusionConfig)
                                  and spec.decoder.distribution_input == "mean_sigma")

        entry = DECODERS[spec.decoder.name]
        self.image_encoder = ImageEncoder(spec.encoder.backbone, 5 if self.five_channel else 3,
                                          spec.encoder.stem_activation,
                                          entry.encoder_levels(spec.decoder))
        self.distribution_encoder = None
        built = entry.build(self.image_encoder.channels, spec)
        self.decoder: nn.Module = built.decoder
        self.distribution_encoder = built.distribution_encoder
        self.traceable = False
        self.head: DepthHead = HEADS[spec.head.name](built.out_channels, spec)

    @classmethod
    def from_network_config(cls, spec: NetworkConfig) -> DeltarNet:
        """The network (random weights) of a :class:`~deltar.models.config.NetworkConfig`."""
        return cls(spec.encoder, spec.decoder, spec.head, spec.inputs, spec.output)

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> DeltarNet:
        """The network (random weights) of a stored config, :meth:`config`'s form.

        Raises:
            ValueError: an unknown section or option, or a bad value (naming it).
        """
        return cls.from_network_config(NetworkConfig.from_dict(config))

    def config(self) -> dict[str, dict[str, Any]]:
        """The network's config as stored in checkpoints and ONNX metadata: one section
        per part (``input``, ``encoder``, ``decoder``, ``head``, ``output``)."""
        return self.network_config.to_dict()

    def contract(self) -> dict[str, Any]:
        """The input and output contract readers need, flat
        (:func:`deltar.contract.network_contract`): ``design_size``, ``image_mean``,
        ``image_std``, ``num_hypotheses``, ``hypothesis_sampling``,
        ``histogram_hypotheses``, ``head``,
        ``no_target_depth``, ``uncertainty_calibration``, ``confidence_blend``, ..."""
        from deltar.contract import network_contract

        return network_contract(self.config())

    def set_output_contract(self, **options: Any) -> DeltarNet:
        """Replace output-contract options fitted after training
        (:data:`~deltar.models.config.OUTPUT_STAGE_OPTIONS`), e.g. after fitting them;
        ``no_target_depth`` (metres) also moves the head's no-target hypothesis.

        Returns:
            The network itself.

        Raises:
            ValueError: another option, a bad value, or ``no_target_depth`` for a head
                that reads no flags.
        """
        unknown = sorted(set(options) - set(OUTPUT_STAGE_OPTIONS))
        if unknown or ("no_target_depth" in options and not self.uses_no_target):
            raise ValueError(f"only {OUTPUT_STAGE_OPTIONS} can be set on a built network "
                             f"(no_target_depth on a head that reads no-target flags), got "
                             f"{sorted(options)}")
        self.network_config = replace(self.network_config,
                                      output=replace(self.network_config.output, **options))
        if "no_target_depth" in options:
            self.head.no_target_depth = self.network_config.output.no_target_depth
        return self

    @property
    def uses_no_target(self) -> bool:
        """Whether the head reads ``zone_no_target`` (then an export takes it as input)."""
        return bool(self.head.uses_no_target)

    @property
    def uses_targets(self) -> bool:
        """Whether the head reads ``zone_targets`` (several targets per zone)."""
        return bool(self.head.uses_targets)

    def set_traceable(self, enabled: bool = True) -> DeltarNet:
        """Switch the network to (or back from) its traceable path, for ONNX export.

        The traceable path computes the same outputs with operators the TorchScript
        tracer records: the zone resampling matrices are built as one-hot products
        (see :mod:`~deltar.models.zone_patches`) and the mViT head avoids PyTorch's
        fused transformer kernel; under ONNX export, descriptors stay in factors for a
        head that reads them. It uses more memory; leave it off otherwise.

        Returns:
            The network itself.
        """
        self.traceable = bool(enabled)
        self.head.traceable = self.traceable
        if hasattr(self.decoder, "factored_export"):  # FactoredDescriptors, export only
            self.decoder.factored_export = self.traceable and self.head.reads_factored_descriptors
        return self

    def forward(
        self,
        image: torch.Tensor,
        hypotheses: torch.Tensor,
        zone_rects: torch.Tensor,
        zone_valid: torch.Tensor,
        zone_mean_sigma: torch.Tensor | None = None,
        zone_no_target: torch.Tensor | None = None,
        zone_targets: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """Estimate depth.

        Args:
            image: (B, 3, H, W) float RGB normalised with ImageNet mean/std; H and W
                divisible by 32.
            hypotheses: (B, Z, K) depth hypotheses per zone, metres (0 for invalid
                zones); Z = n * n zones, row-major.
            zone_rects: (B, Z, 4) float (y0, x0, y1, x1) zone rectangles in pixels of
                ``image``; may run past the image; layouts may differ per sample.
            zone_valid: (B, Z) bool.
            zone_mean_sigma: optional (B, Z, 2) zone mean and sigma in metres, used by
                the mean/sigma and five-channel variants; if None they are estimated
                from ``hypotheses`` (their mean and standard deviation).
            zone_no_target: optional (B, Z) bool, zones whose sensor reported *no target*
                (ST status 255: nothing within range); the "plane_select" head offers
                ``no_target_depth`` there, the other heads ignore it.
            zone_targets: optional (B, Z, T, 2) every target each zone reported,
                ``[distance in metres (0: empty slot), share of the zone]``, target 0 the
                primary reading (:func:`deltar.sensor.targets.target_inputs`);
                the "plane_select" head chooses among them, the other heads ignore it.

        Returns:
            dict with ``depth`` (B, 1, H/2, W/2) metres, ``bin_edges`` (B, N + 1)
            metres and ``uncertainty`` (B, 1, H/2, W/2) metres.
        """
        grid = self.validate_inputs(image, hypotheses, zone_rects, zone_valid, zone_mean_sigma,
                                    zone_no_target, zone_targets)
        valid = zone_valid.bool()
        scale = None
        if self.zone_scale_norm:
            scale = zone_scale(hypotheses, valid, zone_mean_sigma)  # (B,)
            hypotheses = hypotheses / scale[:, None, None]
            if zone_mean_sigma is not None:
                zone_mean_sigma = zone_mean_sigma / scale[:, None, None]
            if zone_targets is not None:
                zone_targets = torch.stack([zone_targets[..., 0] / scale[:, None, None],
                                            zone_targets[..., 1]], dim=-1)
        if (self.mean_sigma_points or self.five_channel) and zone_mean_sigma is None:
            zone_mean_sigma = torch.stack(
                [hypotheses.mean(dim=2), hypotheses.std(dim=2, unbiased=False)], dim=-1
            )
        if self.five_channel:
            maps = paint_zone_maps(zone_mean_sigma, zone_rects, valid, image.shape[-2:])
            image = torch.cat([image, maps.to(image.dtype)], dim=1)
        image_features = self.image_encoder(image)

        decoder_zones = DecoderZones(tuple(image.shape[-2:]))
        if self.distribution_encoder is not None:
            if self.mean_sigma_points:
                points = (zone_mean_sigma * valid[..., None])[:, :, None, :]
            else:
                points = hypotheses[..., None]
            # The encoder lists features fine to coarse; fusion runs coarse to fine.
            zone_features = self.distribution_encoder(points.to(image.dtype))[::-1]
            height, width = image.shape[-2:]
            resamplers = []
            for stride in FUSION_STRIDES:
                window = zone_window(zone_rects, float(stride), grid)
                size = (height // stride, width // stride)
                resamplers.append(ZonePatchResampler(window, size, image.dtype,
                                                     traceable=self.traceable))
            decoder_zones = DecoderZones(tuple(image.shape[-2:]), zone_features, valid,
                                         resamplers)
        features = self.decoder(image_features, decoder_zones)
        zones = ZoneInputs(hypotheses, valid, zone_rects, image.shape[-1] / features.shape[-1],
                           zone_mean_sigma, zone_no_target, scale, zone_targets)
        depth, edges, uncertainty = self.head.predict(features, zones)
        half = (image.shape[-2] // 2, image.shape[-1] // 2)
        if tuple(depth.shape[-2:]) != half:
            # Heads on coarser features: their output is resized to the contract's
            # stride 2 (depth in log space, so that a constant stays constant).
            depth = torch.exp(F.interpolate(torch.log(depth), size=half, mode="bilinear",
                                            align_corners=False))
            uncertainty = F.interpolate(uncertainty, size=half, mode="bilinear",
                                        align_corners=False)
        if scale is not None:
            metric = scale.to(depth.dtype)
            depth = (depth * metric[:, None, None, None]).clamp(self.min_depth, self.max_depth)
            uncertainty = uncertainty * metric[:, None, None, None]
            edges = edges * metric[:, None]
        return {"depth": depth, "bin_edges": edges, "uncertainty": uncertainty}

    def validate_inputs(
        self,
        image: torch.Tensor,
        hypotheses: torch.Tensor,
        zone_rects: torch.Tensor,
        zone_valid: torch.Tensor,
        zone_mean_sigma: torch.Tensor | None = None,
        zone_no_target: torch.Tensor | None = None,
        zone_targets: torch.Tensor | None = None,
    ) -> int:
        """Check shapes and values of the forward inputs; return the zone grid side n.

        Raises:
            ValueError: naming the offending argument.
        """
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be (B, 3, H, W), got {tuple(image.shape)}")
        batch, _, height, width = image.shape
        if height % SIZE_DIVISOR or width % SIZE_DIVISOR:
            raise ValueError(
                f"image height and width must be divisible by {SIZE_DIVISOR}, got {height}x{width}"
            )
        if not torch.isfinite(image).all():
            raise ValueError("image contains NaN or infinite values")
        if hypotheses.ndim != 3 or hypotheses.shape[0] != batch:
            raise ValueError(f"hypotheses must be (B={batch}, Z, K), got {tuple(hypotheses.shape)}")
        zones = hypotheses.shape[1]
        grid = math.isqrt(zones)
        if zones == 0 or grid * grid != zones:
            raise ValueError(f"hypotheses: zone count Z={zones} is not a square grid (16, 64)")
        if not torch.isfinite(hypotheses).all() or (hypotheses < 0).any():
            raise ValueError("hypotheses must be finite and non-negative (metres)")
        if tuple(zone_rects.shape) != (batch, zones, 4):
            raise ValueError(f"zone_rects must be (B={batch}, Z={zones}, 4), got "
                             f"{tuple(zone_rects.shape)}")
        if not torch.isfinite(zone_rects).all():
            raise ValueError("zone_rects contains NaN or infinite values")
        y0, x0, y1, x1 = zone_rects.unbind(-1)
        empty = (y1 <= y0) | (x1 <= x0)
        if empty.any():
            raise ValueError("zone_rects: every zone needs y1 > y0 and x1 > x0")
        if tuple(zone_valid.shape) != (batch, zones):
            raise ValueError(f"zone_valid must be (B={batch}, Z={zones}), got "
                             f"{tuple(zone_valid.shape)}")
        if zone_valid.dtype != torch.bool:
            raise ValueError(f"zone_valid must be a bool tensor, got {zone_valid.dtype}")
        if zone_mean_sigma is not None:
            if tuple(zone_mean_sigma.shape) != (batch, zones, 2):
                raise ValueError(f"zone_mean_sigma must be (B={batch}, Z={zones}, 2), got "
                                 f"{tuple(zone_mean_sigma.shape)}")
            if not torch.isfinite(zone_mean_sigma).all() or (zone_mean_sigma < 0).any():
                raise ValueError("zone_mean_sigma must be finite and non-negative (metres)")
        if zone_no_target is not None:
            if tuple(zone_no_target.shape) != (batch, zones):
                raise ValueError(f"zone_no_target must be (B={batch}, Z={zones}), got "
                                 f"{tuple(zone_no_target.shape)}")
            if zone_no_target.dtype != torch.bool:
                raise ValueError(f"zone_no_target must be a bool tensor, got "
                                 f"{zone_no_target.dtype}")
        if zone_targets is not None:
            if (zone_targets.ndim != 4 or tuple(zone_targets.shape[:2]) != (batch, zones)
                    or zone_targets.shape[-1] != 2 or not 1 <= zone_targets.shape[2] <= 4):
                raise ValueError(f"zone_targets must be (B={batch}, Z={zones}, T, 2) with T in "
                                 f"1..4, got {tuple(zone_targets.shape)}")
            if not torch.isfinite(zone_targets).all() or (zone_targets < 0).any():
                raise ValueError("zone_targets must be finite and non-negative (metres, shares)")
        return grid


def zone_scale(hypotheses: torch.Tensor, zone_valid: torch.Tensor,
               zone_mean_sigma: torch.Tensor | None = None) -> torch.Tensor:
    """Each frame's metric scale: the median of its valid zone means, metres.

    Args:
        hypotheses: (B, Z, K) hypotheses in metres (their mean stands for the zone mean
            when ``zone_mean_sigma`` is None).
        zone_valid: (B, Z) bool.
        zone_mean_sigma: optional (B, Z, 2) zone mean and sigma in metres.

    Returns:
        (B,) scale in metres (>= 1 cm); 1.0 for frames without a valid zone.
    """
    means = zone_mean_sigma[..., 0] if zone_mean_sigma is not None else hypotheses.mean(dim=2)
    valid = zone_valid.bool()
    count = valid.sum(dim=1)
    # The lower median by sorting (exports to ONNX, unlike nanmedian): invalid zones
    # sort last as +inf.
    ordered = means.float().masked_fill(~valid, float("inf")).sort(dim=1).values
    middle = ((count - 1).clamp_min(0) // 2)[:, None]
    median = ordered.gather(1, middle)[:, 0]
    return torch.where(count > 0, median.clamp_min(0.01), torch.ones_like(median))


def paint_zone_maps(
    zone_mean_sigma: torch.Tensor,
    zone_rects: torch.Tensor,
    zone_valid: torch.Tensor,
    size: tuple[int, int],
) -> torch.Tensor:
    """Paint each valid zone's mean and sigma over the pixels whose centre it contains.

    Args:
        zone_mean_sigma: (B, Z, 2) metres.
        zone_rects: (B, Z, 4) (y0, x0, y1, x1) pixels; pixel (i, j) belongs to a zone
            when y0 <= i < y1 and x0 <= j < x1.
        zone_valid: (B, Z) bool.
        size: (H, W) of the output maps.

    Returns:
        (B, 2, H, W) float maps in metres (0 where no valid zone lies).
    """
    rows = torch.arange(size[0], device=zone_rects.device, dtype=zone_rects.dtype)
    cols = torch.arange(size[1], device=zone_rects.device, dtype=zone_rects.dtype)
    in_rows = (rows >= zone_rects[..., 0:1]) & (rows < zone_rects[..., 2:3])
    in_cols = (cols >= zone_rects[..., 1:2]) & (cols < zone_rects[..., 3:4])
    values = zone_mean_sigma * zone_valid[..., None]
    return torch.einsum(
        "bzh,bzw,bzc->bchw", in_rows.to(values.dtype), in_cols.to(values.dtype), values
    )
