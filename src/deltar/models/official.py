"""Load the officially released DELTAR weights (zju3dv/deltar) into :class:`DeltarNet`.

The release's state dict uses its own module names (``img_encoder.conv0..conv4``,
``hist_encoder.*``, ``decoder.*``, ``depth_head.*``, ``conv_out.*``). This module
renames them to this package's modules, reshapes the one parameter laid out
differently (the image positional encoding, stored flat), and reports every key it
could not place. Build the model with ``create_model("deltar-official")``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from deltar.io.torch_file import read_torch_file

# (pattern, replacement) applied in order, first match wins. Patterns are anchored.
_ENCODER_RULES = [
    (r"img_encoder\.conv0\.0\.(.*)", r"image_encoder.backbone.conv_stem.\1"),
    (r"img_encoder\.conv0\.1\.(.*)", r"image_encoder.backbone.bn1.\1"),
    (r"img_encoder\.conv0\.2\.(.*)", r"image_encoder.backbone.blocks.0.\1"),
    (r"img_encoder\.conv1\.(.*)", r"image_encoder.backbone.blocks.1.\1"),
    (r"img_encoder\.conv2\.(.*)", r"image_encoder.backbone.blocks.2.\1"),
    (r"img_encoder\.conv3\.0\.(.*)", r"image_encoder.backbone.blocks.3.\1"),
    (r"img_encoder\.conv3\.1\.(.*)", r"image_encoder.backbone.blocks.4.\1"),
    (r"img_encoder\.conv4\.(.*)", r"image_encoder.backbone.blocks.5.\1"),
]
_ATTENTION_LAYER_NAMES = {
    "q_proj": "query_proj",
    "k_proj": "key_proj",
    "v_proj": "value_proj",
    "merge": "out_proj",
    "mlp": "ffn",
    "norm1": "norm_message",
    "norm2": "norm_out",
}
# The release's cross_atten3/2/1 work at strides 16/8/4: our fusions 0/1/2.
_FUSION_INDEX = {"3": "0", "2": "1", "1": "2"}
_REDUCE_INDEX = {"3": "0", "2": "1", "1": "2"}


def _rename_attention_layer(suffix: str) -> str:
    head, _, rest = suffix.partition(".")
    return f"{_ATTENTION_LAYER_NAMES.get(head, head)}.{rest}"


def official_to_ours(name: str) -> str | None:
    """Our parameter name for one official state-dict key, or None if it has no rule."""
    for pattern, replacement in _ENCODER_RULES:
        if re.fullmatch(pattern, name):
            return re.sub(pattern, replacement, name)
    match = re.fullmatch(
        r"hist_encoder\.hist_extractor(\d)\.pointnet_encoder\.(conv|bn)(\d)\.(.*)", name
    )
    if match:
        block, kind, index, rest = match.groups()
        position = 3 * (int(index) - 1) + (0 if kind == "conv" else 1)
        return f"distribution_encoder.blocks.{int(block) - 1}.mlp.{position}.{rest}"
    match = re.fullmatch(r"decoder\.conv([0-4])\.(.*)", name)
    if match:
        index, rest = match.groups()
        if index == "4":
            return f"decoder.bottleneck.{rest}"
        if index == "0":
            return f"decoder.out_conv.{rest}"
        return f"decoder.reduce.{_REDUCE_INDEX[index]}.{rest}"
    match = re.fullmatch(r"decoder\.up(\d)\._net\.(.*)", name)
    if match:
        return f"decoder.up_blocks.{int(match.group(1)) - 1}.block.{match.group(2)}"
    match = re.fullmatch(r"decoder\.cross_atten(\d)\.(.*)", name)
    if match and match.group(1) in _FUSION_INDEX:
        prefix = f"decoder.fusions.{_FUSION_INDEX[match.group(1)]}"
        rest = match.group(2)
        if rest == "positional_encodings":
            return f"{prefix}.image_position"
        if rest == "positional_encodings2":
            return f"{prefix}.hypothesis_position"
        layer = re.fullmatch(r"layers\.(\d+)\.(.*)", rest)
        if layer is None:
            return None
        index, inner = layer.groups()
        base = f"{prefix}.layers.{index}"
        for official, ours in (("lga.encoder_layer.", "local.layer."),
                               ("gsa.encoder_layer.", "global_.layer.")):
            if inner.startswith(official):
                return f"{base}.{ours}{_rename_attention_layer(inner[len(official):])}"
        if inner.startswith("gsa.sr."):
            return f"{base}.global_.reduce.{inner[len('gsa.sr.'):]}"
        if inner.startswith("gsa.norm."):
            return f"{base}.global_.reduce_norm.{inner[len('gsa.norm.'):]}"
        return f"{base}.{_rename_attention_layer(inner)}"
    head_rules = [
        (r"depth_head\.conv3x3\.(.*)", r"head.range_conv.\1"),
        (r"depth_head\.conv1x1\.(.*)", r"head.global_conv.\1"),
        (r"depth_head\.regressor\.(.*)", r"head.width_regressor.\1"),
        (r"conv_out\.0\.(.*)", r"head.logits_conv.\1"),
    ]
    for pattern, replacement in head_rules:
        if re.fullmatch(pattern, name):
            return re.sub(pattern, replacement, name)
    return None


@dataclass
class LoadReport:
    """What happened when loading official weights.

    Attributes:
        loaded: number of tensors copied into the model.
        unmapped: official keys with no counterpart in the model.
        missing: model keys the official state dict did not provide.
        shape_mismatches: (official key, official shape, model shape) triples.
    """

    loaded: int = 0
    unmapped: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    shape_mismatches: list[tuple[str, tuple, tuple]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when every key was placed and nothing is missing."""
        return not (self.unmapped or self.missing or self.shape_mismatches)

    def summary(self) -> str:
        """One-paragraph human-readable account."""
        parts = [f"loaded {self.loaded} tensors"]
        if self.unmapped:
            parts.append(f"{len(self.unmapped)} unmapped (e.g. {self.unmapped[:3]})")
        if self.missing:
            parts.append(f"{len(self.missing)} missing (e.g. {self.missing[:3]})")
        if self.shape_mismatches:
            parts.append(f"{len(self.shape_mismatches)} shape mismatches "
                         f"(e.g. {self.shape_mismatches[:2]})")
        return "; ".join(parts)


def unwrap_state_dict(checkpoint: Mapping) -> dict[str, torch.Tensor]:
    """Plain state dict from a checkpoint: unwraps ``{"model": ...}`` / ``{"state_dict": ...}``
    and strips ``module.`` prefixes (from DataParallel)."""
    state = checkpoint
    for wrapper in ("model", "state_dict"):
        if isinstance(state, Mapping) and isinstance(state.get(wrapper), Mapping):
            state = state[wrapper]
    if not isinstance(state, Mapping) or not state:
        raise ValueError("checkpoint holds no state dict")
    plain = {}
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            continue
        plain[key.removeprefix("module.")] = value
    return plain


def convert_official_state_dict(
    official: Mapping[str, torch.Tensor], model: nn.Module
) -> tuple[dict[str, torch.Tensor], LoadReport]:
    """Rename (and reshape) an official state dict for ``model``.

    Args:
        official: the release's state dict (already unwrapped).
        model: the target :class:`DeltarNet` (its shapes decide reshapes).

    Returns:
        (converted state dict, report). Values are cast to the model's float dtype.
    """
    target = model.state_dict()
    report = LoadReport()
    converted: dict[str, torch.Tensor] = {}
    for key, value in official.items():
        ours = official_to_ours(key)
        if ours is None or ours not in target:
            report.unmapped.append(key)
            continue
        expected = target[ours]
        if ours.endswith("image_position") and value.ndim == 2:
            # Stored flat (H * W, C) in the release; ours is (H, W, C).
            if value.numel() == expected.numel():
                value = value.reshape(expected.shape)
        if tuple(value.shape) != tuple(expected.shape):
            report.shape_mismatches.append((key, tuple(value.shape), tuple(expected.shape)))
            continue
        converted[ours] = value.to(expected.dtype) if value.is_floating_point() else value
    report.loaded = len(converted)
    report.missing = [key for key in target if key not in converted]
    return converted, report


def load_official_weights(
    model: nn.Module, path_or_state_dict: str | Path | Mapping, strict: bool = True
) -> LoadReport:
    """Load the released weights (file or state dict) into ``model``.

    Args:
        model: a :class:`DeltarNet` built with ``create_model("deltar-official")``.
        path_or_state_dict: path of ``nyu.pt`` (or any checkpoint of that layout),
            or the loaded dict; ``{"model": ...}`` wrappers and ``module.`` prefixes
            are accepted; float16 tensors are cast to the model's dtype.
        strict: raise if any key is unmapped, missing or of the wrong shape.

    Returns:
        A :class:`LoadReport`.

    Raises:
        FileNotFoundError: the path does not exist.
        ValueError: the file holds no state dict, or (strict) keys do not match.
    """
    if isinstance(path_or_state_dict, (str, Path)):
        checkpoint = read_torch_file(path_or_state_dict, "official weights",
                                     weights_only=True)
    else:
        checkpoint = path_or_state_dict
    converted, report = convert_official_state_dict(unwrap_state_dict(checkpoint), model)
    if strict and not report.ok:
        raise ValueError(f"official weights do not match the model: {report.summary()}")
    model.load_state_dict(converted, strict=False)
    return report
