"""Reading PyTorch files (checkpoints, weights, fixtures) with errors that name the file."""

from __future__ import annotations

import os
from typing import Any

from deltar.io.input_file import input_file


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
        FileNotFoundError / IsADirectoryError: ``"<what> not found: <path>"``, ``"<what>
            <path> is a folder, not a file"``; ``"... not a regular file"`` (ValueError).
        ValueError: ``"<path>: cannot read <what>: ..."`` for a corrupt or foreign file.
    """
    import torch

    path = input_file(path, what)
    try:
        return torch.load(path, map_location=map_location, weights_only=weights_only)
    except Exception as err:  # torch raises several types for corrupt files
        raise ValueError(f"{path}: cannot read {what}: {_reason(err)}") from err


def _reason(err: Exception) -> str:
    """A short, safe explanation of a ``torch.load`` failure.

    PyTorch's own messages run over many lines and suggest loading with
    ``weights_only=False``, which runs arbitrary code from the file: never repeated here.
    """
    import re

    text = str(err)
    if "Unsupported operand" in text:  # not a pickle stream at all (a text file ...)
        return "not a PyTorch file, or a corrupt or truncated one"
    if "Weights only load failed" in text:
        found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
        names = f" (it refers to {found.group(1)})" if found else ""
        return ("it holds Python objects besides tensors and plain containers, which safe "
                f"loading refuses{names}; re-save it with tensors only")
    if "zip archive" in text:
        return "corrupt or truncated PyTorch file"
    return "not a PyTorch file, or a corrupt or truncated one"
