"""Reading JSON files with errors that name the file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def read_json(path: str | os.PathLike, what: str) -> Any:
    """Parse a UTF-8 JSON file.

    Args:
        path: the file.
        what: what the file is, for the error message (e.g. ``"calibration file"``).

    Raises:
        FileNotFoundError: ``"<what> not found: <path>"``.
        ValueError: ``"<path>: corrupt JSON: ..."`` for unreadable or invalid JSON.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: corrupt JSON: {err}") from err


def read_split_filenames(path: str | os.PathLike, split: str, what: str) -> list[str]:
    """File names of one split of a ``{"split": [{"filename": ...}, ...]}`` index.

    The layout of the DELTAR release's ``data.json`` (ZJU-L5) and NYU split files.

    Raises:
        FileNotFoundError: no such file.
        ValueError: corrupt JSON, no such split (the message lists the splits), or
            entries without a ``"filename"`` string.
    """
    index = read_json(path, what)
    if not isinstance(index, dict) or split not in index:
        keys = sorted(index) if isinstance(index, dict) else []
        raise ValueError(f"{what} {path} has no split {split!r} (splits: {keys})")
    entries = index[split]
    if not isinstance(entries, list) or not all(
            isinstance(e, dict) and isinstance(e.get("filename"), str) for e in entries):
        raise ValueError(f"{what} {path}: split {split!r} must be a list of "
                         '{"filename": "..."} entries')
    return [e["filename"] for e in entries]
