"""Reading the training configuration: YAML files, ``key=value`` overrides, dicts.

Loading checks every key against the schema of :mod:`deltar.training.config` (unknown
keys raise a ``ValueError`` naming them with their full dotted path) and every value
(types, ranges, choices). ``key=value`` overrides use dotted paths into the same tree,
e.g. ``optim.lr=1e-4`` or ``data.sources.0.path=/data/nyu.json``; values are parsed as
YAML (``1e-4`` -> float, ``[416, 544]`` -> list, ``null`` -> None).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any

import yaml

from deltar.io.input_file import input_file, reading
from deltar.training.config import TrainConfig


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Build and validate a :class:`TrainConfig` from a nested dict.

    Raises:
        ValueError: unknown keys (named with their dotted paths), wrong types or values.
    """
    config = _build(TrainConfig, data, "")
    config.validate()
    return config


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> TrainConfig:
    """Read a YAML configuration file and apply ``key=value`` overrides.

    Args:
        path: YAML file.
        overrides: dotted ``key=value`` strings applied in order, e.g. ``optim.lr=1e-4``.

    Returns:
        The validated configuration.

    Raises:
        FileNotFoundError / IsADirectoryError: the path is missing or a folder.
        ValueError: invalid YAML, unknown keys or invalid values (an
            :class:`~deltar.io.input_file.InputFileError` for an unreadable file: not
            UTF-8, nested too deeply ...).
    """
    file = input_file(path, "training config")
    with reading(file, "training config"):
        try:
            data = yaml.safe_load(file.read_bytes().decode("utf-8")) or {}
        except yaml.YAMLError as err:
            raise ValueError(f"training config {file} is not valid YAML: {err}") from err
    if not isinstance(data, dict):
        raise ValueError(f"training config {file} must be a mapping at the top level")
    for item in overrides:
        apply_override(data, item)
    try:
        return config_from_dict(data)
    except (ValueError, TypeError, AttributeError) as err:
        raise ValueError(f"training config {file}: {err}") from err


def apply_override(data: dict[str, Any], item: str) -> None:
    """Set one dotted ``key=value`` override in a nested dict (in place).

    List elements are addressed by index (``data.sources.0.path=...``). Intermediate
    mappings are created when missing; whether the key exists in the schema is checked
    when the dict is turned into a :class:`TrainConfig`.

    Raises:
        ValueError: malformed override or a path through a non-container.
    """
    key, sep, text = item.partition("=")
    if not sep or not key.strip():
        raise ValueError(f"override must look like key=value, got {item!r}")
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ValueError(f"override {item!r}: value is not valid YAML: {err}") from err
    parts = key.strip().split(".")
    node: Any = data
    for depth, part in enumerate(parts):
        last = depth == len(parts) - 1
        where = ".".join(parts[:depth + 1])
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ValueError(f"override {item!r}: {where} is not an index of a list of "
                                 f"{len(node)}")
            if last:
                node[int(part)] = value
            else:
                node = node[int(part)]
        elif isinstance(node, dict):
            if last:
                node[part] = value
            else:
                node = node.setdefault(part, {})
                if node is None:
                    raise ValueError(f"override {item!r}: {where} is null")
        else:
            raise ValueError(f"override {item!r}: {'.'.join(parts[:depth])} is not a mapping")


def _build(cls: type, data: Any, where: str) -> Any:
    """Recursively turn a dict into dataclass ``cls``, checking keys and value types."""
    label = where or "config"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(f"{label} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - fields)
    if unknown:
        names = [f"{where}.{k}" if where else str(k) for k in unknown]
        raise ValueError(f"unknown config keys {names}; known keys under {label}: "
                         f"{sorted(fields)}")
    values = {}
    for name, value in data.items():
        path = f"{where}.{name}" if where else name
        values[name] = _convert(hints[name], value, path)
    return cls(**values)


def _convert(hint: Any, value: Any, path: str) -> Any:
    """Check (and gently convert, e.g. int -> float) one value against its type hint."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None:
            if type(None) in options:
                return None
            raise ValueError(f"{path} must not be null")
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, path)
            except ValueError as err:
                errors.append(str(err))
        raise ValueError(errors[0] if len(errors) == 1 else
                         f"{path}: {value!r} matches none of {hint}")
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, path)
    if origin is list:
        (item_hint,) = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{path} must be a list, got {value!r}")
        return [_convert(item_hint, v, f"{path}.{i}") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ValueError(f"{path} must be a mapping, got {value!r}")
        return dict(value)
    if hint is Any:
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{path} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{path} must be an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, str):
            # PyYAML (YAML 1.1) reads exponents without a dot, like 1e-4, as strings.
            try:
                return float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{path} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{path} must be a string, got {value!r}")
        return value
    raise TypeError(f"unsupported type hint {hint} at {path}")

