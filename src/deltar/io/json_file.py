"""Reading JSON files with errors that name the file."""

from __future__ import annotations

import json
import os
from pathlib import PurePath
from typing import Any

from deltar.io.input_file import InputFileError, input_file, reading


def read_json(path: str | os.PathLike, what: str) -> Any:
    """Parse a UTF-8 JSON file.

    Args:
        path: the file.
        what: what the file is, for the error message (e.g. ``"calibration file"``).

    Raises:
        FileNotFoundError / IsADirectoryError / InputFileError: the path is missing, a
            folder or not a regular file (:func:`~deltar.io.input_file.input_file`).
        InputFileError: ``"<path>: corrupt JSON: ..."`` for invalid JSON, ``"<path>:
            cannot read <what>: ..."`` for anything else (not UTF-8, nested too deeply,
            a number beyond any float).
    """
    path = input_file(path, what)
    with reading(path, what):
        try:
            return json.loads(path.read_bytes().decode("utf-8"))
        except json.JSONDecodeError as err:
            raise InputFileError(path, f"{path}: corrupt JSON: {err}") from err


def read_split_filenames(path: str | os.PathLike, split: str, what: str, *,
                         relative: bool = False) -> list[str]:
    """File names of one split of a ``{"split": [{"filename": ...}, ...]}`` index.

    The layout of the DELTAR release's ``data.json`` (ZJU-L5) and NYU split files.

    Args:
        path: the index file.
        split: the list to read.
        what: what the file is, for the error message (e.g. ``"ZJU-L5 index"``).
        relative: refuse entries that are absolute paths, empty or hold ``..``: names
            of files beside the index, which must not reach outside its folder.

    Raises:
        FileNotFoundError: no such file.
        ValueError: corrupt JSON, no such split (the message lists the splits),
            entries without a ``"filename"`` string, or (``relative``) an entry that is
            not a relative path without ``..``.
    """
    index = read_json(path, what)

    def is_list(value) -> bool:
        return isinstance(value, list) and all(
            isinstance(e, dict) and isinstance(e.get("filename"), str) for e in value)

    if not isinstance(index, dict) or (split not in index and
                                       not any(is_list(v) for v in index.values())):
        raise ValueError(f"{path} is no {what}: no list of {{\"filename\": ...}} entries "
                         "under a split name (e.g. {\"test\": [{\"filename\": ...}]})")
    if split not in index:
        raise ValueError(f"{what} {path} has no split {split!r} (splits: {sorted(index)})")
    entries = index[split]
    if not is_list(entries):
        raise ValueError(f"{what} {path}: split {split!r} must be a list of "
                         '{"filename": "..."} entries')
    names = [e["filename"] for e in entries]
    if relative:
        for name in names:
            parts = PurePath(name).parts
            if PurePath(name).is_absolute() or ".." in parts or not parts:
                raise ValueError(f"{what} {path}: {name!r} must be a relative path without "
                                 "'..'")
    return names
