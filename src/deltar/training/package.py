"""Turn a training result into a small deltar checkpoint to ship or share."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from deltar.io.atomic import atomic_path
from deltar.training.module import _load_weights_file, export_model


def package_checkpoint(source: str | os.PathLike, destination: str | os.PathLike, *,
                       float16: bool = True, model_config: dict[str, Any] | None = None,
                       overwrite: bool = False) -> Path:
    """Write a run's network as a deltar checkpoint, optionally in float16.

    Args:
        source: a run's ``model.pt`` or a Lightning ``.ckpt`` (EMA weights when the run
            averaged them).
        destination: output ``.pt`` file (written atomically; never the source).
        float16: store floating-point tensors as float16 (half the size; they are cast
            back to the model's dtype on load).
        model_config: flat options (:data:`deltar.models.config.FLAT_OPTIONS`)
            overriding the ones the file records.
        overwrite: replace an existing destination.

    Returns:
        The destination path.
    """
    src, dst = Path(source), Path(destination)
    if dst.resolve() == src.resolve():
        raise ValueError(f"destination {dst} is the source file; refusing to overwrite it")
    model, recipe = _load_weights_file(str(src), model_config=model_config)
    payload = export_model(model, recipe["preset"])
    if float16:
        payload["state_dict"] = {k: v.half() if v.is_floating_point() else v
                                 for k, v in payload["state_dict"].items()}
    with atomic_path(dst, overwrite=overwrite) as tmp:
        torch.save(payload, tmp)
    return dst
