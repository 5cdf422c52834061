"""The network's input contract, defined once: a leaf every package may import.

Weights carry their own contract in their config (``image_mean`` / ``image_std``,
``hypothesis_sampling``, ``design_size``; see :mod:`deltar.models.checkpoint`); these
are the values it can take and the defaults new models start from; the one reader of
that contract from a stored network config (:func:`network_contract`, also for ONNX
files, without PyTorch); and the one image normaliser (:func:`normalise_image`) that
maps camera images onto the contract.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

#: The network's input height and width must be multiples of this (pixels): the image
#: encoder's coarsest stride.
SIZE_DIVISOR = 32
#: ImageNet statistics (RGB, images in [0, 1]): the release's input normalisation.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: How per-zone depth hypotheses are drawn from a zone's (mean, sigma): "icdf" (the
#: release: evenly spaced quantiles of the Gaussian) or "uniform" (random draws).
HYPOTHESIS_SAMPLINGS = ("icdf", "uniform")
#: The model presets (``deltar.models.list_presets()``, which imports PyTorch), named
#: here so that a typo is told from a missing extra without it.
PRESET_NAMES = ("deltar-lite", "deltar-official", "deltar-paper", "deltar-select")
#: The sections of a stored network config (:class:`deltar.models.config.NetworkConfig`).
NETWORK_CONFIG_SECTIONS = ("input", "encoder", "decoder", "head", "output")
#: What :func:`network_contract` returns: the input section's keys, the head's name and
#: the output section's keys.
_CONTRACT_INPUT_KEYS = ("design_size", "image_mean", "image_std", "num_hypotheses",
                        "hypothesis_sampling", "histogram_hypotheses", "zone_scale_norm")
_CONTRACT_OUTPUT_KEYS = ("min_depth", "max_depth", "no_target_depth",
                         "uncertainty_calibration", "confidence_blend",
                         "no_target_min_neighbour_m", "zone_outlier_rule",
                         "zone_consistency")


def is_sectioned_config(config: Mapping[str, Any]) -> bool:
    """Whether a stored network config has per-part sections (format 3), not flat
    options (format 2, whose ``head`` and ``decoder`` are names, not sections)."""
    return isinstance(config.get("input"), Mapping)


def network_contract(config: Mapping[str, Any]) -> dict[str, Any]:
    """The contract a stored network config carries, as one flat dict.

    Reads both forms a config is stored in: the per-part sections of checkpoint format 3
    and of ONNX files exported since (``{"input": {...}, "head": {"name": ...}, ...}``)
    and the flat options of format 2.

    Args:
        config: the stored network config.

    Returns:
        ``design_size`` (H, W pixels), ``image_mean`` / ``image_std``,
        ``num_hypotheses``, ``hypothesis_sampling``, ``histogram_hypotheses``,
        ``zone_scale_norm``, ``head`` (its
        name), ``min_depth`` / ``max_depth`` / ``no_target_depth`` (metres) and
        ``uncertainty_calibration`` / ``confidence_blend`` (dicts or None) and
        ``no_target_min_neighbour_m`` (metres or None), ``zone_outlier_rule`` (dict
        or None) and ``zone_consistency`` (in [0, 1]): those the config holds.
    """
    keys = (*_CONTRACT_INPUT_KEYS, "head", *_CONTRACT_OUTPUT_KEYS)
    if not is_sectioned_config(config):  # format 2: flat options of the same names
        return {key: config[key] for key in keys if key in config}
    head = config.get("head") or {}
    flat = {**(config.get("input") or {}), **(config.get("output") or {})}
    if "name" in head:
        flat["head"] = head["name"]
    return {key: flat[key] for key in keys if key in flat}


def as_switch(name: str, value: Any) -> bool:
    """An on/off option as a bool: True / False (numpy's too) or their names as text in
    any case (a quoted YAML value); anything else is a ``ValueError`` naming the option.
    (``bool("false")`` would be True.)"""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):
        return value.strip().lower() == "true"
    raise ValueError(f"{name} must be true or false, got {value!r}")


def check_strength(strength: Any, name: str = "zone_consistency") -> float:
    """A strength in [0, 1] (the output contract's ``zone_consistency``) as a float; a
    ``ValueError`` naming ``name`` for anything else (booleans, NaN, text)."""
    if isinstance(strength, bool) or not isinstance(strength, numbers.Real) or \
            not (math.isfinite(strength) and 0.0 <= strength <= 1.0):
        raise ValueError(f"{name} must be a number in [0, 1], got {strength!r}")
    return float(strength)


def normalise_image(image: np.ndarray, mean: Sequence[float] = IMAGENET_MEAN,
                    std: Sequence[float] = IMAGENET_STD) -> np.ndarray:
    """An RGB image as the network's input: ``(rgb - mean) / std`` with rgb in [0, 1].

    The release's formula, in float32 and in its order (divide by 255, subtract the mean,
    divide by the std). Training, the parity checks and the tests use it; the
    estimator's batched form (:func:`deltar.inference.preprocess.normalise_images`)
    resizes as it normalises and is tested against it.

    Args:
        image: (H, W, 3) RGB, uint8 (0-255) or float in [0, 1] (e.g. after augmentation).
        mean, std: per RGB channel, the network's input contract
            (``InputConfig.image_mean`` / ``image_std``); ImageNet's by default.

    Returns:
        (3, H, W) float32.
    """
    image = np.asarray(image)
    if image.dtype == np.uint8:
        image = image.astype(np.float32) / np.float32(255.0)
    mean = np.asarray(mean, dtype=np.float32)
    std = np.asarray(std, dtype=np.float32)
    return ((image - mean) / std).transpose(2, 0, 1).astype(np.float32)
