"""Named model presets and ablation switches: ``create_model(name, **overrides)``."""

from __future__ import annotations

from typing import Any

from deltar.models.network import DeltarNet

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
    # Small and fast for CPUs: MobileNetV3 encoder, narrow decoder, one cross- and one
    # self-attention layer per fusion scale, and the zone-prior head (starts from the
    # sensor's reading, so it trains on little data; see docs/models.md).
    "deltar-lite": {
        "backbone": "tf_mobilenetv3_large_minimal_100",
        "decoder_channels": (128, 128, 64, 32, 16),
        "head_channels": 32,
        "head": "zone_prior",
        "n_bins": 64,
        "min_depth": 1e-3,
        "max_depth": 10.0,
        "num_hypotheses": 16,
        "fusion_layers": ("hist2image", "image"),
        "cross_heads": 2,
        "self_heads": 2,
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


def create_model(preset: str, **overrides: Any) -> DeltarNet:
    """Build a :class:`DeltarNet` from a named preset (random weights, no download).

    Args:
        preset: one of :func:`list_presets`.
        **overrides: constructor arguments replacing the preset's, e.g.
            ``**ABLATIONS["feature_concat"]`` or ``n_bins=128``.

    Returns:
        The model in training mode.

    Raises:
        ValueError: unknown preset (the message lists the known ones) or bad override.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; known presets: {list_presets()}")
    arguments = {**PRESETS[preset], **overrides}
    try:
        return DeltarNet(**arguments)
    except TypeError as error:
        raise ValueError(f"bad override for preset {preset!r}: {error}") from error
