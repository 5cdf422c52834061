"""The network's configuration, one small frozen dataclass per part.

:class:`NetworkConfig` holds five parts: :class:`InputConfig` (the input contract the
weights were trained with), :class:`EncoderConfig`, the decoder (:class:`FusionConfig`
or :class:`DescriptorConfig`, by name in :data:`DECODER_CONFIGS`), the head
(:class:`HeadConfig`, or :class:`PlaneSelectConfig` with that head's own options, by
name in :data:`HEAD_CONFIGS`) and :class:`OutputConfig` (depth range and what the
estimator reads about the outputs). :class:`~deltar.models.network.DeltarNet` is built from them;
``NetworkConfig.to_dict()`` / ``NetworkConfig.from_dict()`` give the nested dict that
checkpoints (format 3) and ONNX metadata store, one section per part.

The flat option names of format-2 checkpoints (``backbone``, ``n_bins``,
``decoder_channels``, ...) remain the keyword overrides of
:func:`~deltar.models.presets.create_model` and of the training config's
``model.overrides``: :data:`FLAT_OPTIONS` says which part and field each one sets.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from deltar.contract import (
    HYPOTHESIS_SAMPLINGS,
    IMAGENET_MEAN,
    IMAGENET_STD,
    NETWORK_CONFIG_SECTIONS,
    SIZE_DIVISOR,
    as_switch,
    check_strength,
)
from deltar.models.encoders import FEATURE_STRIDES
from deltar.models.fusion import FUSION_MODES, LAYER_KINDS
from deltar.sensor.no_target import check_min_neighbour_m
from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M
from deltar.sensor.zone_outliers import outlier_rule_from_dict

#: Heads that choose among the zone readings (the only ones the descriptor decoder,
#: which gives the head no zone information, can feed).
SELECTING_HEADS = ("zone_select", "plane_select")
#: Paper ablation (Table 4): how the zone distributions enter the fusion decoder.
DISTRIBUTION_INPUTS = ("hypotheses", "mean_sigma")
#: Paper ablation (Table 4): what the image encoder reads.
IMAGE_INPUTS = ("rgb", "rgb_zone_maps")


@dataclass(frozen=True)
class InputConfig:
    """The input contract the weights were trained with (readers take it from the file).

    Attributes:
        design_size: (H, W) pixels, the input size the positional encodings are laid
            out for (the resolution it was trained at); divisible by 32.
        image_mean: per-channel (RGB) mean the image is normalised with, for images in
            [0, 1] (ImageNet's by default; (0.5, 0.5, 0.5) for the EfficientNet-Lite
            ImageNet weights).
        image_std: per-channel standard deviation of that normalisation.
        num_hypotheses: K depth hypotheses per zone the network is designed for.
        hypothesis_sampling: how the data pipeline draws the hypotheses ("icdf" or
            "uniform"); read by the estimator, does not change the network.
        histogram_hypotheses: the network was trained on hypotheses drawn from the
            zones' histograms where a reading carries them (CNH, THDR3K sets): the data
            pipeline and the estimator then draw them so; False (default): always from
            each zone's (mean, sigma), histograms or not. A network trained on one kind
            reads the other worse (benchmarks/RESULTS.md); does not change the network.
        zone_scale_norm: take the metric scale from the sensor: the zone readings are
            divided by each frame's median valid zone mean ``s`` before the network sees
            them and depth, uncertainty and bin edges multiplied by ``s`` afterwards
            (frames without a valid zone use ``s = 1``).
    """

    design_size: tuple[int, int] = (480, 640)
    image_mean: tuple[float, float, float] = IMAGENET_MEAN
    image_std: tuple[float, float, float] = IMAGENET_STD
    num_hypotheses: int = 16
    hypothesis_sampling: str = "icdf"
    histogram_hypotheses: bool = False
    zone_scale_norm: bool = False

    def __post_init__(self) -> None:
        _set(self, "design_size", tuple(int(v) for v in self.design_size))
        _set(self, "image_mean", tuple(float(v) for v in self.image_mean))
        _set(self, "image_std", tuple(float(v) for v in self.image_std))
        for switch in ("zone_scale_norm", "histogram_hypotheses"):
            _set(self, switch, as_switch(switch, getattr(self, switch)))
        if (len(self.design_size) != 2 or self.design_size[0] % SIZE_DIVISOR
                or self.design_size[1] % SIZE_DIVISOR or min(self.design_size) < SIZE_DIVISOR):
            raise ValueError(f"design_size must be (H, W) positive and divisible by "
                             f"{SIZE_DIVISOR}: {self.design_size}")
        if len(self.image_mean) != 3 or len(self.image_std) != 3 or min(self.image_std) <= 0:
            raise ValueError(f"image_mean and image_std need 3 values (std > 0), got "
                             f"{self.image_mean}, {self.image_std}")
        if int(self.num_hypotheses) < 1:
            raise ValueError(f"num_hypotheses must be >= 1, got {self.num_hypotheses}")
        _check_choice("hypothesis_sampling", self.hypothesis_sampling, HYPOTHESIS_SAMPLINGS)


@dataclass(frozen=True)
class EncoderConfig:
    """The image encoder (:class:`~deltar.models.encoders.ImageEncoder`).

    Attributes:
        backbone: timm backbone name.
        stem_activation: keep the activation after the stem norm (False reproduces the
            released weights).
        image_input: "rgb"; paper ablation "rgb_zone_maps" (zone mean and sigma painted
            into two extra input channels, no distribution branch).
    """

    backbone: str = "tf_efficientnetv2_b3"
    stem_activation: bool = True
    image_input: str = "rgb"

    def __post_init__(self) -> None:
        _set(self, "stem_activation", as_switch("stem_activation", self.stem_activation))
        _check_choice("image_input", self.image_input, IMAGE_INPUTS)


@dataclass(frozen=True)
class FusionConfig:
    """The zone-fusion decoder of the paper (:class:`~deltar.models.decoder.FusionDecoder`)
    and the distribution encoder it fuses.

    Attributes:
        name: "fusion".
        channels: five decoder widths; the fusion widths are half of the second to
            fourth, and the PointNet widths are those, fine to coarse.
        out_channels: width of the features fed to the head.
        fusion: zone fusion mode, "attention" (the release); the others of
            :data:`~deltar.models.fusion.FUSION_MODES` are paper ablations.
        fusion_layers: order of "hist2image" / "image" layers at each fusion scale.
        cross_heads: heads of the zone-to-image attention.
        self_heads: heads of the image self attention.
        distribution_input: "hypotheses" (K sampled depths per zone); paper ablation
            "mean_sigma" (one (mean, sigma) point per zone).
    """

    name: str = "fusion"
    channels: tuple[int, ...] = (256, 256, 128, 64, 32)
    out_channels: int = 128
    fusion: str = "attention"
    fusion_layers: tuple[str, ...] = ("hist2image", "image", "hist2image", "image")
    cross_heads: int = 4
    self_heads: int = 8
    distribution_input: str = "hypotheses"

    def __post_init__(self) -> None:
        _check_kind(self, "decoder", DECODER_CONFIGS)
        _set(self, "channels", tuple(int(v) for v in self.channels))
        _set(self, "fusion_layers", tuple(str(v) for v in self.fusion_layers))
        _check_choice("fusion", self.fusion, FUSION_MODES)
        _check_choice("distribution_input", self.distribution_input, DISTRIBUTION_INPUTS)
        if len(self.channels) != 5:
            raise ValueError(f"decoder_channels needs five widths, got {self.channels}")
        if any(kind not in LAYER_KINDS for kind in self.fusion_layers):
            raise ValueError(f"fusion_layers must be among {LAYER_KINDS}, got "
                             f"{self.fusion_layers}")


@dataclass(frozen=True)
class DescriptorConfig:
    """No decoder to train: the head compares frozen-encoder descriptors at stride 4
    (:class:`~deltar.models.affinity.EncoderDescriptors`); the zone readings enter only
    through the head, so a head of :data:`SELECTING_HEADS` is required.

    Attributes:
        name: "descriptors".
        strides: the encoder strides the descriptors use.
    """

    name: str = "descriptors"
    strides: tuple[int, ...] = (8, 16)

    def __post_init__(self) -> None:
        _check_kind(self, "decoder", DECODER_CONFIGS)
        _set(self, "strides", tuple(int(v) for v in self.strides))
        if not self.strides or any(s not in FEATURE_STRIDES for s in self.strides):
            raise ValueError(f"descriptor strides must be among {FEATURE_STRIDES}, got "
                             f"{self.strides}")


#: Each decoder's config class by name.
DECODER_CONFIGS: dict[str, type] = {"fusion": FusionConfig, "descriptors": DescriptorConfig}
DecoderConfig = FusionConfig | DescriptorConfig


@dataclass(frozen=True)
class HeadConfig:
    """A depth head that takes only its bin count.

    Attributes:
        name: "bins" (release), "mvit" (paper's AdaBins refinement), "zone_prior"
            (log-ratio bins around a smooth prior from the zone means), "zone_select"
            (an image-guided choice among the zone readings); paper ablation "direct"
            (no refinement, no bins). "plane_select" has its own
            :class:`PlaneSelectConfig`.
        n_bins: number of depth bins N (unused by "direct").
    """

    name: str = "bins"
    n_bins: int = 256

    def __post_init__(self) -> None:
        _check_kind(self, "head", HEAD_CONFIGS)
        if int(self.n_bins) < 1:
            raise ValueError(f"n_bins must be >= 1, got {self.n_bins}")


@dataclass(frozen=True)
class PlaneSelectConfig(HeadConfig):
    """The plane-select head (:mod:`deltar.models.heads.plane_select`): the zones' local
    planes chosen by feature affinity.

    Attributes:
        name: "plane_select".
        n_bins: number of bins of the reported edges.
        temperature: initial affinity temperature.
        planar: hypotheses are the zones' local planes (else constants).
    """

    name: str = "plane_select"
    n_bins: int = 64
    temperature: float = 5.0
    planar: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        _set(self, "temperature", float(self.temperature))
        _set(self, "planar", as_switch("planar", self.planar))


#: Each head's config class by name (one file each under :mod:`deltar.models.heads`;
#: built by :data:`deltar.models.network.HEADS`).
HEAD_CONFIGS: dict[str, type] = {"bins": HeadConfig, "mvit": HeadConfig, "direct": HeadConfig,
                                 "zone_prior": HeadConfig, "zone_select": HeadConfig,
                                 "plane_select": PlaneSelectConfig}


@dataclass(frozen=True)
class OutputConfig:
    """The depth range and what the estimator reads about the outputs.

    Attributes:
        min_depth: smallest depth, metres.
        max_depth: largest depth, metres.
        no_target_depth: metres, the "plane_select" hypothesis of a zone that reported
            no target (beyond the sensor's range), when ``zone_no_target`` is given (the
            estimator fills such zones at this depth too); None ignores the flags.
        uncertainty_calibration: how the estimator maps the network's spread to a
            calibrated sigma
            (:meth:`deltar.inference.uncertainty.UncertaintyCalibration.to_dict`), or
            None (the spread is returned as it is); does not change the network.
        confidence_blend: the coefficients of the estimator's blend of the network's
            depth with the zones' colorization fill
            (:meth:`deltar.inference.blend.ConfidenceBlend.to_dict`), or None (the
            estimator's default for plane-select networks); does not change the network.
        no_target_min_neighbour_m: metres; for frames without no-target flags, the
            estimator reads an invalid zone as no target when a valid neighbour reads at
            least this much (:func:`deltar.sensor.no_target.infer_no_target`); None
            reads none so. Fitted with the output stage; does not change the network.
        zone_outlier_rule: when the estimator sets aside valid zones that disagree with
            every neighbour (:meth:`deltar.sensor.zone_outliers.OutlierRule.to_dict`) or
            that a learned detector finds biased
            (:meth:`deltar.sensor.zone_outlier_detector.OutlierDetector.to_dict`), or
            None (never). Fitted with the output stage; does not change the network.
        zone_consistency: in [0, 1], how far the estimator moves the network's depth to
            reproduce each zone's reading (:mod:`deltar.inference.zone_consistency`); 0
            (default) not at all. Fitted with the output stage; does not change the network.
    """

    min_depth: float = 1e-3
    max_depth: float = 10.0
    no_target_depth: float | None = NO_TARGET_DEPTH_M
    uncertainty_calibration: dict[str, Any] | None = None
    confidence_blend: dict[str, Any] | None = None
    no_target_min_neighbour_m: float | None = None
    zone_outlier_rule: dict[str, Any] | None = None
    zone_consistency: float = 0.0

    def __post_init__(self) -> None:
        _set(self, "zone_consistency", check_strength(self.zone_consistency))
        if not 0 < self.min_depth < self.max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {self.min_depth}, "
                             f"{self.max_depth}")
        far = self.no_target_depth
        if far is not None:
            far = float(far)
            if not (math.isfinite(far) and self.min_depth < far <= self.max_depth):
                raise ValueError(f"no_target_depth must lie in ({self.min_depth}, "
                                 f"{self.max_depth}] m, got {far}")
        _set(self, "no_target_depth", far)
        for name in ("uncertainty_calibration", "confidence_blend"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, Mapping):
                raise ValueError(f"{name} must be a dict or None, got {value!r}")
            _set(self, name, None if value is None else dict(value))
        _set(self, "no_target_min_neighbour_m", check_min_neighbour_m(
            self.no_target_min_neighbour_m, "no_target_min_neighbour_m"))
        if self.zone_outlier_rule is not None:  # checked, kept in its stored form
            _set(self, "zone_outlier_rule",
                 outlier_rule_from_dict(self.zone_outlier_rule).to_dict())


#: Output-contract options fitted after training (``deltar fit-uncertainty``)
#: (:meth:`deltar.models.network.DeltarNet.set_output_contract`); all but
#: ``no_target_depth`` (the plane-select head's no-target hypothesis) leave the network
#: as it is.
OUTPUT_STAGE_OPTIONS = ("uncertainty_calibration", "confidence_blend",
                        "no_target_min_neighbour_m", "zone_outlier_rule", "no_target_depth",
                        "zone_consistency")

#: Each section's config classes by kind name; parts of one kind only under None.
PART_CLASSES: dict[str, dict[str | None, type]] = {
    "input": {None: InputConfig}, "encoder": {None: EncoderConfig},
    "decoder": DECODER_CONFIGS, "head": HEAD_CONFIGS, "output": {None: OutputConfig}}
assert tuple(PART_CLASSES) == NETWORK_CONFIG_SECTIONS

#: Each flat option name (format-2 checkpoints, ``create_model`` overrides, the
#: training config's ``model.overrides``) -> (section, field) it sets.
FLAT_OPTIONS: dict[str, tuple[str, str]] = {
    **{name: ("input", name) for name in ("design_size", "image_mean", "image_std",
                                          "num_hypotheses", "hypothesis_sampling",
                                          "histogram_hypotheses", "zone_scale_norm")},
    **{name: ("encoder", name) for name in ("backbone", "stem_activation", "image_input")},
    "decoder": ("decoder", "name"),
    "decoder_channels": ("decoder", "channels"),
    "head_channels": ("decoder", "out_channels"),
    **{name: ("decoder", name) for name in ("fusion", "fusion_layers", "cross_heads",
                                            "self_heads", "distribution_input")},
    "descriptor_strides": ("decoder", "strides"),
    "head": ("head", "name"),
    "n_bins": ("head", "n_bins"),
    "select_temperature": ("head", "temperature"),
    "planar": ("head", "planar"),
    **{name: ("output", name) for name in ("min_depth", "max_depth", "no_target_depth",
                                           "uncertainty_calibration", "confidence_blend",
                                           "no_target_min_neighbour_m",
                                           "zone_outlier_rule", "zone_consistency")},
}


@dataclass(frozen=True)
class NetworkConfig:
    """The whole network: its five parts, checked together.

    Raises:
        ValueError: a part of the wrong type, or parts that do not fit together (the
            descriptor decoder with a head that does not select among the zones, or
            with the five-channel image input).
    """

    inputs: InputConfig = field(default_factory=InputConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    decoder: DecoderConfig = field(default_factory=FusionConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def __post_init__(self) -> None:
        for (section, classes), part in zip(PART_CLASSES.items(), self._values(), strict=True):
            if type(part) not in classes.values():
                raise ValueError(f"the {section} part must be one of "
                                 f"{sorted({c.__name__ for c in classes.values()})}, got "
                                 f"{part!r}")
        if self.decoder.name == "descriptors" and self.head.name not in SELECTING_HEADS:
            raise ValueError(f"decoder 'descriptors' gives the head no zone information: it "
                             f"needs head 'zone_select' or 'plane_select', got "
                             f"{self.head.name!r}")
        if self.decoder.name == "descriptors" and self.encoder.image_input != "rgb":
            raise ValueError("decoder 'descriptors' takes image_input 'rgb' only")

    def _values(self) -> tuple[Any, ...]:
        return self.inputs, self.encoder, self.decoder, self.head, self.output

    def parts(self) -> dict[str, Any]:
        """The parts by section name (``input``, ``encoder``, ``decoder``, ``head``,
        ``output``)."""
        return dict(zip(PART_CLASSES, self._values(), strict=True))

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The nested dict checkpoints and ONNX metadata store: one section per part
        (the decoder's and the head's with their ``name``)."""
        return {section: asdict(part) for section, part in self.parts().items()}

    @classmethod
    def from_dict(cls, config: Mapping[str, Any]) -> NetworkConfig:
        """Read :meth:`to_dict`'s nested form; a missing section or field takes its
        default (a decoder or head section without ``name``: "fusion", "bins").

        Raises:
            ValueError: an unknown section or option (naming it), or a bad value.
        """
        unknown = set(config) - set(PART_CLASSES)
        if unknown:
            raise ValueError(f"unknown network config sections {sorted(unknown)}; known: "
                             f"{list(PART_CLASSES)}")
        defaults = cls().parts()
        parts = []
        for section, classes in PART_CLASSES.items():
            values = dict(config.get(section) or {})
            kind = values.get("name", getattr(defaults[section], "name", None))
            if kind not in classes:
                _check_choice(section, kind, tuple(classes))
            part_class = classes[kind]
            extra = set(values) - _field_names(part_class)
            if extra:
                raise ValueError(f"unknown {section} options {sorted(extra)} for "
                                 f"{part_class.__name__}; known: "
                                 f"{sorted(_field_names(part_class))}")
            parts.append(part_class(**values))
        return cls(*parts)

    @classmethod
    def from_flat(cls, options: Mapping[str, Any]) -> NetworkConfig:
        """Build from flat option names (:data:`FLAT_OPTIONS`), defaults elsewhere."""
        return cls().with_options(**options)

    def with_options(self, **options: Any) -> NetworkConfig:
        """A copy with flat options (:data:`FLAT_OPTIONS`) replaced, e.g. ``n_bins=128``.

        A new ``decoder`` or ``head`` name switches that part's kind: the options the
        two kinds share (``n_bins``) are kept, the others start from the new kind's
        defaults.

        Raises:
            ValueError: an unknown option (the message lists the known ones), an option
                the chosen decoder or head does not have, or a bad value.
        """
        return self._replaced(options, drop_inapplicable=False)

    def with_stored_options(self, options: Mapping[str, Any]) -> NetworkConfig:
        """As :meth:`with_options`, for format-2 files, which store every option of
        every kind: options the chosen decoder and head do not have are dropped."""
        return self._replaced(options, drop_inapplicable=True)

    def _replaced(self, options: Mapping[str, Any], drop_inapplicable: bool
                  ) -> NetworkConfig:
        unknown = sorted(set(options) - set(FLAT_OPTIONS))
        if unknown:
            raise ValueError(f"unknown network options {unknown}; known: "
                             f"{sorted(FLAT_OPTIONS)}")
        changes: dict[str, dict[str, Any]] = {}
        for option, value in options.items():
            section, name = FLAT_OPTIONS[option]
            changes.setdefault(section, {})[name] = value
        parts = self.parts()
        for section, values in changes.items():
            current, classes = parts[section], PART_CLASSES[section]
            kind = values.get("name", getattr(current, "name", None))
            if kind not in classes:
                _check_choice(section, kind, tuple(classes))
            part_class = classes[kind]
            names = _field_names(part_class)
            inapplicable = sorted(set(values) - names)
            if inapplicable and not drop_inapplicable:
                flat = [o for o, target in FLAT_OPTIONS.items()
                        if target[0] == section and target[1] in inapplicable]
                raise ValueError(f"{section} {kind!r} has no option {flat}")
            kept = {k: v for k, v in asdict(current).items() if k in names}
            kept.update({k: v for k, v in values.items() if k in names})
            parts[section] = part_class(**kept)
        return NetworkConfig(*parts.values())

    def flat_options(self) -> dict[str, Any]:
        """The flat options (:data:`FLAT_OPTIONS`) of this config's parts with their
        values (those of the chosen decoder and head kinds only)."""
        parts = self.parts()
        return {option: getattr(parts[section], name)
                for option, (section, name) in FLAT_OPTIONS.items()
                if name in _field_names(type(parts[section]))}


def _field_names(part_class: type) -> set[str]:
    return {f.name for f in fields(part_class)}


def _check_kind(part: Any, section: str, classes: Mapping[str, type]) -> None:
    """A decoder's or head's ``name`` must be one its class stands for."""
    _check_choice(section, part.name, tuple(classes))
    if classes[part.name] is not type(part):
        raise ValueError(f"{section} {part.name!r} takes a {classes[part.name].__name__}, "
                         f"not a {type(part).__name__}")


def _set(instance: Any, name: str, value: Any) -> None:
    """Normalise a field of a frozen dataclass in ``__post_init__`` (lists to tuples)."""
    object.__setattr__(instance, name, value)


def _check_choice(name: str, value: Any, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
