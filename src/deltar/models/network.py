"""DeltarNet: dense metric depth from an RGB image and multi-zone ToF distributions."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from deltar.contract import HYPOTHESIS_SAMPLINGS, IMAGENET_MEAN, IMAGENET_STD, SIZE_DIVISOR
from deltar.models.affinity import EncoderDescriptors, descriptor_levels
from deltar.models.decoder import FUSION_STRIDES, DecoderZones, FusionDecoder
from deltar.models.encoders import FEATURE_STRIDES, DistributionEncoder, ImageEncoder
from deltar.models.fusion import FUSION_MODES
from deltar.models.heads.base import DepthHead, ZoneInputs
from deltar.models.heads.bins import BinsHead
from deltar.models.heads.direct import DirectDepthHead
from deltar.models.heads.mvit import MiniViTHead
from deltar.models.heads.plane_select import PlanarSelectHead
from deltar.models.heads.zone_prior import ZonePriorHead
from deltar.models.heads.zone_select import ZoneSelectHead
from deltar.models.zone_patches import ZonePatchResampler, zone_window
from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M

#: Each head by name: a builder from (input feature width, the network's config).
HEADS: dict[str, Callable[[int, dict[str, Any]], DepthHead]] = {
    "bins": lambda width, c: BinsHead(width, c["n_bins"], width, min_depth=c["min_depth"],
                                      max_depth=c["max_depth"]),
    "mvit": lambda width, c: MiniViTHead(
        width, c["n_bins"], width, min_depth=c["min_depth"], max_depth=c["max_depth"],
        design_tokens=(c["design_size"][0] // 32, c["design_size"][1] // 32)),
    "direct": lambda width, c: DirectDepthHead(width, c["min_depth"], c["max_depth"]),
    "zone_prior": lambda width, c: ZonePriorHead(width, c["n_bins"], width,
                                                 min_depth=c["min_depth"],
                                                 max_depth=c["max_depth"]),
    "zone_select": lambda width, c: ZoneSelectHead(width, width, c["n_bins"],
                                                   min_depth=c["min_depth"],
                                                   max_depth=c["max_depth"]),
    "plane_select": lambda width, c: PlanarSelectHead(
        c["select_temperature"], c["planar"], n_bins=c["n_bins"], min_depth=c["min_depth"],
        max_depth=c["max_depth"], no_target_depth=c["no_target_depth"]),
}
#: Heads that choose among the zone readings (the only ones the descriptor decoder,
#: which gives the head no zone information, can feed).
SELECTING_HEADS = ("zone_select", "plane_select")
#: Where the head's features come from: the zone-fusion decoder, or the encoder alone.
DECODERS = ("fusion", "descriptors")
DISTRIBUTION_INPUTS = ("hypotheses", "mean_sigma")
IMAGE_INPUTS = ("rgb", "rgb_zone_maps")


class DeltarNet(nn.Module):
    """The DELTAR network (Li et al., ECCV 2022), configurable for its ablations.

    Args:
        backbone: timm backbone name for the image encoder.
        stem_activation: keep the activation after the stem norm (False reproduces the
            released weights, see :class:`~deltar.models.encoders.ImageEncoder`).
        decoder_channels: five decoder widths; the fusion widths are half of the
            second to fourth, and the PointNet widths are those, fine to coarse.
        head: a name of :data:`HEADS`, one file each under :mod:`deltar.models.heads`:
            "bins" (release), "mvit" (paper's AdaBins refinement), "direct" (the
            no-refinement ablation), "zone_prior" (log-ratio bins around a smooth prior
            from the zone means), "zone_select" (an image-guided choice among the zone
            readings) or "plane_select" (the zones' local planes chosen by feature
            affinity).
        head_channels: width of the decoder output fed to the head.
        n_bins: number of depth bins N.
        min_depth: smallest depth, metres.
        max_depth: largest depth, metres.
        num_hypotheses: K hypotheses per zone the model is designed for.
        distribution_input: "hypotheses" (K sampled depths per zone) or "mean_sigma"
            (mean/variance PointNet ablation: one (mean, sigma) point per zone).
        image_input: "rgb", or "rgb_zone_maps" (five-channel ablation: zone mean and
            sigma painted into two extra input channels; no distribution branch).
        fusion: zone fusion mode, one of
            :data:`~deltar.models.fusion.FUSION_MODES`.
        fusion_layers: order of "hist2image" / "image" layers at each fusion scale.
        cross_heads: heads of the zone-to-image attention.
        self_heads: heads of the image self attention.
        design_size: (H, W) input size the positional encodings are laid out for.
        hypothesis_sampling: how the data pipeline samples hypotheses ("icdf" or
            "uniform"); part of the input contract recorded in :attr:`config` (read by
            the estimator), does not change the network.
        image_mean: per-channel (RGB) mean the input image is normalised with, for
            images in [0, 1]; input contract, recorded in :attr:`config` (ImageNet's by
            default; (0.5, 0.5, 0.5) for the EfficientNet-Lite ImageNet weights).
        image_std: per-channel standard deviation of that normalisation.
        zone_scale_norm: take the metric scale from the sensor: divide the zone readings
            by each frame's median valid zone mean ``s`` before the network sees them and
            multiply depth, uncertainty and bin edges by ``s`` afterwards, so that
            scaling every zone reading by ``k`` scales the output by ``k`` (up to the
            ``min_depth``/``max_depth`` clamp). Frames without a valid zone use ``s = 1``.
        decoder: "fusion" (the zone-fusion decoder of the paper) or "descriptors" (no
            decoder: the head compares frozen-encoder descriptors,
            :class:`~deltar.models.affinity.EncoderDescriptors`, at stride 4; the zone
            readings enter only through the head, so a selecting head is required).
        descriptor_strides: encoder strides the descriptors use.
        select_temperature: initial affinity temperature of the "plane_select" head.
        planar: "plane_select" hypotheses are the zones' local planes (else constants).
        no_target_depth: metres, the "plane_select" hypothesis of a zone that reported no
            target (beyond the sensor's range), when ``zone_no_target`` is given; None
            ignores the flags (checkpoints saved before them load that way).
        uncertainty_calibration: output contract, recorded in :attr:`config` (read by the
            estimator), does not change the network: how the estimator maps this
            network's spread to a calibrated sigma
            (:meth:`deltar.inference.uncertainty.UncertaintyCalibration.to_dict`), or
            None (the spread is returned as it is).
        confidence_blend: output contract, recorded in :attr:`config` (read by the
            estimator), does not change the network: the coefficients of the estimator's
            blend of this network's depth with the zones' colorization fill
            (:meth:`deltar.inference.blend.ConfidenceBlend.to_dict`), or None (the
            estimator's default for plane-select networks).
    """

    def __init__(
        self,
        backbone: str = "tf_efficientnetv2_b3",
        stem_activation: bool = True,
        decoder_channels: Sequence[int] = (256, 256, 128, 64, 32),
        head: str = "bins",
        head_channels: int = 128,
        n_bins: int = 256,
        min_depth: float = 1e-3,
        max_depth: float = 10.0,
        num_hypotheses: int = 16,
        distribution_input: str = "hypotheses",
        image_input: str = "rgb",
        fusion: str = "attention",
        fusion_layers: Sequence[str] = ("hist2image", "image", "hist2image", "image"),
        cross_heads: int = 4,
        self_heads: int = 8,
        design_size: tuple[int, int] = (480, 640),
        hypothesis_sampling: str = "icdf",
        image_mean: Sequence[float] = IMAGENET_MEAN,
        image_std: Sequence[float] = IMAGENET_STD,
        zone_scale_norm: bool = False,
        decoder: str = "fusion",
        descriptor_strides: Sequence[int] = (8, 16),
        select_temperature: float = 5.0,
        planar: bool = True,
        no_target_depth: float | None = NO_TARGET_DEPTH_M,
        uncertainty_calibration: dict | None = None,
        confidence_blend: dict | None = None,
    ) -> None:
        super().__init__()
        _check_choice("head", head, tuple(HEADS))
        _check_choice("distribution_input", distribution_input, DISTRIBUTION_INPUTS)
        _check_choice("image_input", image_input, IMAGE_INPUTS)
        _check_choice("fusion", fusion, FUSION_MODES)
        _check_choice("hypothesis_sampling", hypothesis_sampling, HYPOTHESIS_SAMPLINGS)
        _check_choice("decoder", decoder, DECODERS)
        if decoder == "descriptors" and head not in SELECTING_HEADS:
            raise ValueError(f"decoder 'descriptors' gives the head no zone information: it "
                             f"needs head 'zone_select' or 'plane_select', got {head!r}")
        if decoder == "descriptors" and image_input != "rgb":
            raise ValueError("decoder 'descriptors' takes image_input 'rgb' only")
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        if design_size[0] % SIZE_DIVISOR or design_size[1] % SIZE_DIVISOR:
            raise ValueError(f"design_size must be divisible by {SIZE_DIVISOR}: {design_size}")
        if len(image_mean) != 3 or len(image_std) != 3 or min(image_std) <= 0:
            raise ValueError(f"image_mean and image_std need 3 values (std > 0), got "
                             f"{image_mean}, {image_std}")
        self.config = {
            "backbone": backbone,
            "stem_activation": stem_activation,
            "decoder_channels": tuple(decoder_channels),
            "head": head,
            "head_channels": head_channels,
            "n_bins": n_bins,
            "min_depth": min_depth,
            "max_depth": max_depth,
            "num_hypotheses": num_hypotheses,
            "distribution_input": distribution_input,
            "image_input": image_input,
            "fusion": fusion,
            "fusion_layers": tuple(fusion_layers),
            "cross_heads": cross_heads,
            "self_heads": self_heads,
            "design_size": tuple(design_size),
            "hypothesis_sampling": hypothesis_sampling,
            "image_mean": tuple(float(v) for v in image_mean),
            "image_std": tuple(float(v) for v in image_std),
            "zone_scale_norm": bool(zone_scale_norm),
            "decoder": decoder,
            "descriptor_strides": tuple(int(v) for v in descriptor_strides),
            "select_temperature": float(select_temperature),
            "planar": bool(planar),
            "no_target_depth": None if no_target_depth is None else float(no_target_depth),
            "uncertainty_calibration": None if uncertainty_calibration is None
            else dict(uncertainty_calibration),
            "confidence_blend": None if confidence_blend is None else dict(confidence_blend),
        }
        self.zone_scale_norm = bool(zone_scale_norm)
        self.min_depth = min_depth
        self.max_depth = max_depth
        self.five_channel = image_input == "rgb_zone_maps"
        self.mean_sigma_points = distribution_input == "mean_sigma"

        in_channels = 5 if self.five_channel else 3
        # The descriptor decoder reads the encoder up to its coarsest chosen stride only.
        levels = (descriptor_levels(descriptor_strides) if decoder == "descriptors"
                  else len(FEATURE_STRIDES))
        self.image_encoder = ImageEncoder(backbone, in_channels, stem_activation, levels)
        self.distribution_encoder = None
        self.decoder: FusionDecoder | EncoderDescriptors
        if decoder == "descriptors":
            self.decoder = EncoderDescriptors(self.image_encoder.channels, descriptor_strides)
            head_channels = self.decoder.channels
        else:
            self.decoder, self.distribution_encoder = self._fusion_decoder()
        self.traceable = False
        self.head: DepthHead = HEADS[head](head_channels, self.config)

    def _fusion_decoder(self) -> tuple[FusionDecoder, DistributionEncoder | None]:
        """The zone-fusion decoder and the distribution encoder it fuses, from the config."""
        c = self.config
        fusion_kwargs = None
        if not self.five_channel:
            fusion_kwargs = {"num_hypotheses": 1 if self.mean_sigma_points else
                             c["num_hypotheses"], "layer_order": c["fusion_layers"],
                             "mode": c["fusion"], "cross_heads": c["cross_heads"],
                             "self_heads": c["self_heads"]}
        decoder = FusionDecoder(self.image_encoder.channels, c["decoder_channels"],
                                c["head_channels"], fusion_kwargs, c["design_size"])
        if self.five_channel:
            return decoder, None
        return decoder, DistributionEncoder(point_dim=2 if self.mean_sigma_points else 1,
                                            widths=decoder.fusion_dims[::-1])

    @property
    def uses_no_target(self) -> bool:
        """Whether the head reads ``zone_no_target`` (then an export takes it as input)."""
        return bool(self.head.uses_no_target)

    def set_traceable(self, enabled: bool = True) -> DeltarNet:
        """Switch the network to (or back from) its traceable path, for ONNX export.

        The traceable path computes the same outputs with operators the TorchScript
        tracer records: the zone resampling matrices are built as one-hot products
        (see :mod:`~deltar.models.zone_patches`) and the mViT head avoids PyTorch's
        fused transformer kernel. It uses more memory; leave it off otherwise.

        Returns:
            The network itself.
        """
        self.traceable = bool(enabled)
        self.head.traceable = self.traceable
        return self

    def forward(
        self,
        image: torch.Tensor,
        hypotheses: torch.Tensor,
        zone_rects: torch.Tensor,
        zone_valid: torch.Tensor,
        zone_mean_sigma: torch.Tensor | None = None,
        zone_no_target: torch.Tensor | None = None,
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

        Returns:
            dict with ``depth`` (B, 1, H/2, W/2) metres, ``bin_edges`` (B, N + 1)
            metres and ``uncertainty`` (B, 1, H/2, W/2) metres.
        """
        grid = self.validate_inputs(image, hypotheses, zone_rects, zone_valid, zone_mean_sigma,
                                    zone_no_target)
        valid = zone_valid.bool()
        scale = None
        if self.zone_scale_norm:
            scale = zone_scale(hypotheses, valid, zone_mean_sigma)  # (B,)
            hypotheses = hypotheses / scale[:, None, None]
            if zone_mean_sigma is not None:
                zone_mean_sigma = zone_mean_sigma / scale[:, None, None]
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
                           zone_mean_sigma, zone_no_target, scale)
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
            raise ValueError(
                f"hypotheses must be (B={batch}, Z, K), got {tuple(hypotheses.shape)}"
            )
        zones = hypotheses.shape[1]
        grid = math.isqrt(zones)
        if zones == 0 or grid * grid != zones:
            raise ValueError(f"hypotheses: zone count Z={zones} is not a square grid (16, 64)")
        if not torch.isfinite(hypotheses).all() or (hypotheses < 0).any():
            raise ValueError("hypotheses must be finite and non-negative (metres)")
        if tuple(zone_rects.shape) != (batch, zones, 4):
            raise ValueError(
                f"zone_rects must be (B={batch}, Z={zones}, 4), got {tuple(zone_rects.shape)}"
            )
        if not torch.isfinite(zone_rects).all():
            raise ValueError("zone_rects contains NaN or infinite values")
        y0, x0, y1, x1 = zone_rects.unbind(-1)
        empty = (y1 <= y0) | (x1 <= x0)
        if empty.any():
            raise ValueError("zone_rects: every zone needs y1 > y0 and x1 > x0")
        if tuple(zone_valid.shape) != (batch, zones):
            raise ValueError(
                f"zone_valid must be (B={batch}, Z={zones}), got {tuple(zone_valid.shape)}"
            )
        if zone_valid.dtype != torch.bool:
            raise ValueError(f"zone_valid must be a bool tensor, got {zone_valid.dtype}")
        if zone_mean_sigma is not None:
            if tuple(zone_mean_sigma.shape) != (batch, zones, 2):
                raise ValueError(
                    f"zone_mean_sigma must be (B={batch}, Z={zones}, 2), "
                    f"got {tuple(zone_mean_sigma.shape)}"
                )
            if not torch.isfinite(zone_mean_sigma).all() or (zone_mean_sigma < 0).any():
                raise ValueError("zone_mean_sigma must be finite and non-negative (metres)")
        if zone_no_target is not None:
            if tuple(zone_no_target.shape) != (batch, zones):
                raise ValueError(f"zone_no_target must be (B={batch}, Z={zones}), got "
                                 f"{tuple(zone_no_target.shape)}")
            if zone_no_target.dtype != torch.bool:
                raise ValueError(f"zone_no_target must be a bool tensor, got "
                                 f"{zone_no_target.dtype}")
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


def _check_choice(name: str, value: str, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
