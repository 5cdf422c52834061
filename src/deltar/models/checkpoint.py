"""The deltar checkpoint: a network's weights with its whole input contract.

One format for every producer and reader (training's ``model.pt``, packaged and bundled
models, the estimator, export and evaluation). A ``torch.save`` file holding::

    {"format": "deltar.checkpoint", "format_version": 3,
     "preset": "deltar-lite",            # the create_model preset it was built from
     "config": {"input": {...}, "encoder": {...}, "decoder": {...},
                "head": {...}, "output": {...}},   # DeltarNet.config()
     "state_dict": {...}}                # DeltarNet.state_dict(), tensors

The config is the network's own :meth:`DeltarNet.config`, one section per part
(:mod:`deltar.models.config`), so it carries the input contract of the weights
(``input``: ``image_mean`` / ``image_std``, ``design_size``, ``hypothesis_sampling``,
``histogram_hypotheses``, ``num_hypotheses``, ``zone_scale_norm``) and the output
contract (``output``). Readers
take these from the file, never from a preset's current defaults.

Format 2 stored the same options flat (``{"backbone": ..., "n_bins": ..., ...}``, the
names of :data:`~deltar.models.config.FLAT_OPTIONS`); such files (the bundled weights,
earlier training runs) are read with the same state-dict keys. Files of the first format
version (before the contract keys) are refused: no model that ships or that a documented
command wrote is of that version.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from deltar.models.config import NetworkConfig
from deltar.models.network import DeltarNet
from deltar.models.presets import PRESETS

CHECKPOINT_FORMAT = "deltar.checkpoint"
#: The version this deltar writes.
CHECKPOINT_FORMAT_VERSION = 3
#: The versions it reads: 2 (flat options) and 3 (per-part sections).
READABLE_FORMAT_VERSIONS = (2, 3)
#: Format-2 options that were removed, with the only value they could take in a file
#: a documented path wrote (the bundled model and training runs store them): such a key
#: is dropped; any other value describes a network this deltar cannot build.
RETIRED_OPTIONS: dict[str, Any] = {"bin_norm": "linear", "decoder_block": "conv",
                                   "decoder_convs": (2, 2, 2, 2), "decoder_out_kernel": 3}


def checkpoint_payload(model: DeltarNet, preset: str) -> dict[str, Any]:
    """The dict a checkpoint file holds (see the module docstring), float32 weights on CPU.

    Args:
        model: the network.
        preset: the ``create_model`` preset it was built from.
    """
    return {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_FORMAT_VERSION,
            "preset": str(preset), "config": model.config(),
            "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}


def save_checkpoint(path: str | os.PathLike, model: DeltarNet, preset: str, *,
                    overwrite: bool = False) -> Path:
    """Write a model as a deltar checkpoint, atomically.

    Args:
        path: destination file (``.pt``).
        model: the network; its full ``config()`` is stored.
        preset: the preset it was built from (a ``create_model`` name).
        overwrite: replace an existing file (default: ``FileExistsError``).

    Returns:
        The written path.
    """
    from deltar.io.atomic import atomic_path

    with atomic_path(path, overwrite=overwrite) as tmp:
        torch.save(checkpoint_payload(model, preset), tmp)
    return Path(path)


def network_config_from_stored(preset: str, config: dict[str, Any], format_version: int = 3,
                                overrides: dict[str, Any] | None = None) -> NetworkConfig:
    """The parts' configs of a stored config, in either readable format.

    Args:
        preset: the ``create_model`` preset name the file records (a format-2 option
            missing from the file takes the preset's value, as it always did).
        config: the stored config: per-part sections (format 3) or flat options
            (format 2; lists become tuples).
        format_version: the file's format version (2 or 3).
        overrides: flat options (:data:`~deltar.models.config.FLAT_OPTIONS`) replacing
            the stored ones.

    Raises:
        ValueError: unknown preset or version, a removed option with a value other than
            the one it always had, or a config the network does not accept.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; known presets: {sorted(PRESETS)}")
    if format_version == 3:
        spec = NetworkConfig.from_dict(config)
    elif format_version == 2:
        config = {k: tuple(v) if isinstance(v, list) else v for k, v in config.items()}
        for key, only in RETIRED_OPTIONS.items():
            if key in config and config.pop(key) != only:
                raise ValueError(f"config option {key!r} was removed; only {only!r} is read")
        # Weights saved before the no-target flags existed keep the behaviour they were
        # measured with: they ignore the flags.
        config.setdefault("no_target_depth", None)
        spec = PRESETS[preset].with_stored_options(config)
    else:
        raise ValueError(f"unsupported checkpoint format_version {format_version!r} (this "
                         f"deltar reads versions {READABLE_FORMAT_VERSIONS})")
    return spec.with_options(**(overrides or {}))


def model_from_config(preset: str, config: dict[str, Any], format_version: int = 3,
                      overrides: dict[str, Any] | None = None) -> DeltarNet:
    """Rebuild a network (random weights) from a checkpoint's preset and config.

    Args: as :func:`network_config_from_stored`.

    Raises:
        ValueError: unknown preset or a config the network does not accept.
    """
    return DeltarNet.from_network_config(
        network_config_from_stored(preset, config, format_version, overrides))


def load_checkpoint(path: str | os.PathLike) -> tuple[DeltarNet, str, dict[str, Any]]:
    """Read a deltar checkpoint and build its model.

    Returns:
        (model in eval mode, preset name, the model's full config: :meth:`DeltarNet.config`,
        per-part sections, whichever format the file has).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a deltar checkpoint, or its weights do not fit its config.
    """
    from deltar.io.torch_file import read_torch_file

    path = Path(path)
    payload = read_torch_file(path, "checkpoint", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a deltar checkpoint (expected a dict with format "
                         f"{CHECKPOINT_FORMAT!r}; official weights: kind='official', --official)")
    version = payload.get("format_version")
    if version not in READABLE_FORMAT_VERSIONS:
        raise ValueError(f"{path}: unsupported checkpoint format_version {version!r} (this "
                         f"deltar reads versions {READABLE_FORMAT_VERSIONS})")
    for key in ("preset", "config", "state_dict"):
        if key not in payload:
            raise ValueError(f"{path}: checkpoint has no {key!r}")
    preset = str(payload["preset"])
    try:
        model = model_from_config(preset, dict(payload["config"]), version)
        model.load_state_dict(payload["state_dict"])
    except (RuntimeError, ValueError) as err:
        raise ValueError(f"{path}: weights do not fit preset {preset!r}: {err}") from err
    return model.eval(), preset, model.config()
