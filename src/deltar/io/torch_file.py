"""Reading PyTorch files (checkpoints, weights, fixtures) with errors that name the file."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any


def read_torch_file(path: str | os.PathLike, what: str, *, weights_only: bool,
                    map_location: Any = "cpu") -> Any:
    """Load a ``torch.save`` file.

    Args:
        path: the file.
        what: what the file is, for the error messages (e.g. ``"checkpoint"``).
        weights_only: ``torch.load``'s safe mode (tensors and plain containers only);
            False only for files this project wrote or trusted fixtures.
        map_location: where tensors are loaded (CPU by default).

    Raises:
        FileNotFoundError: ``"<what> not found: <path>"``.
        ValueError: ``"<path>: cannot read <what>: ..."`` for a corrupt or foreign file.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=weights_only)
    except Exception as err:  # torch raises several types for corrupt files
        raise ValueError(f"{path}: cannot read {what}: {err}") from err
