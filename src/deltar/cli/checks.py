"""Checks a command runs before any long work: outputs, devices, displays, numbers.

Each raises ``ValueError`` (bad input, exit 1) or ``typer.BadParameter`` (usage, exit 2)
with a message naming the option, so a mistake costs milliseconds, not a model load.
None of them imports torch unless the check needs it.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterable
from pathlib import Path

import typer


def output_folder(path: Path, option: str) -> Path:
    """Check that ``path`` is, or can become, a folder this process can write in.

    Nothing is left behind: the nearest existing ancestor must be a writable folder,
    which a hidden probe file, created and removed at once, proves. Permission bits alone
    do not (root may "write" in /proc, or on a read-only mount, and cannot).

    Args:
        path: the output folder.
        option: the option naming it, for the message (e.g. ``"--out"``).

    Raises:
        ValueError: ``path`` (or an ancestor) is a file, or the folder is not writable.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{option} {path} is a file, not a folder")
    _can_write_in(path, option, path)
    return path


def _can_write_in(folder: Path, option: str, named: Path) -> None:
    """Check that ``folder``'s nearest existing ancestor is a folder a file can be created
    in; messages name ``option`` and ``named`` (the user's output path)."""
    ancestor = folder
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ValueError(f"{option} {named}: {ancestor} is a file, not a folder")
    from deltar.io.atomic import prove_writable

    try:  # the reason as the system gives it (permission denied, read-only file system)
        prove_writable(ancestor)
    except OSError as err:
        raise ValueError(f"{option} {named}: cannot write in {ancestor} "
                         f"({(err.strerror or str(err)).lower()})") from None


def output_file(path: Path, option: str, overwrite: bool) -> Path:
    """Check that ``path`` can be written: not a folder, absent unless ``overwrite``.

    Raises:
        ValueError / FileExistsError: naming ``option`` and the file.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{option} {path} is a folder, not a file")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{option} {path} exists; pass --overwrite to replace it")
    _can_write_in(path.parent, option, path)
    return path


def refuse_unused_options(given: dict[str, bool], what_for: str, why: str) -> None:
    """Refuse options that the command would otherwise silently ignore.

    Args:
        given: option name -> whether the user gave it.
        what_for: what those options are for (``"for hardware recording"``).
        why: why they do not apply here.

    Raises:
        typer.BadParameter: naming the given ones, e.g. ``--camera and --sensor are for
            hardware recording; <why>``.
    """
    names = [name for name, on in given.items() if on]
    if names:
        raise typer.BadParameter(f"{' and '.join(names)} {'is' if len(names) == 1 else 'are'} "
                                 f"{what_for}; {why}", param_hint=names[0])


def existing_outputs(paths: Iterable[Path], option: str = "--out", *,
                     resumable: bool = False) -> None:
    """Refuse to start when outputs exist; the message names ``--overwrite`` and, for a
    command that can resume (``resumable``), ``--skip-existing``.

    Raises:
        FileExistsError: naming how many exist and the first few.
    """
    existing = [str(p) for p in paths if p.exists()]
    if existing:
        shown = ", ".join(existing[:3]) + (" ..." if len(existing) > 3 else "")
        resume = " or --skip-existing to keep them and write the rest" if resumable else ""
        raise FileExistsError(f"{option}: refusing to overwrite {len(existing)} existing "
                              f"output file(s) ({shown}); pass --overwrite to replace "
                              f"them{resume}")


def torch_device(name: str, option: str = "--device") -> str:
    """Check that torch can run on device ``name`` here (e.g. ``cpu``, ``cuda:0``):
    :func:`deltar.inference.checks.check_device` as a usage error naming ``option``.

    Raises:
        typer.BadParameter: unknown device, PyTorch not installed (naming the extra), or
            no such GPU on this machine.
    """
    from deltar.extras import torch_available
    from deltar.inference.checks import DEVICE_NAME, check_device

    # Told apart before torch is imported: a typo is a typo in the base install too.
    if not DEVICE_NAME.fullmatch(name):
        raise typer.BadParameter(f"unknown device {name!r}; use cpu, cuda, cuda:N or mps",
                                 param_hint=option)
    if not torch_available():
        raise typer.BadParameter(f"{name!r} runs the PyTorch backend, which the 'torch' extra "
                                 'installs: pip install "deltar[torch]" (without it the '
                                 "bundled model runs on the CPU)", param_hint=option)
    try:
        return check_device(name, option)
    except ValueError as err:
        raise typer.BadParameter(str(err).removeprefix(f"{option} ").removeprefix(
            f"{option}: "), param_hint=option) from None


def has_display() -> bool:
    """Whether a window can be shown: on Linux, DISPLAY or WAYLAND_DISPLAY is set."""
    return not sys.platform.startswith("linux") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def display(option: str = "--show") -> None:
    """Check that an OpenCV window can open (a display and a GUI build of OpenCV).

    Raises:
        ValueError: naming ``option`` and what is missing.
    """
    if not has_display():
        raise ValueError(f"{option} needs a display (DISPLAY is not set); write the frames "
                         "with --out DIR instead")
    import cv2

    try:
        cv2.namedWindow("deltar")
        cv2.destroyWindow("deltar")
    except cv2.error:
        raise ValueError(f"{option}: this OpenCV cannot open windows (a headless build?); "
                         "write the frames with --out DIR instead") from None


def finite(value: float, option: str, *, positive: bool = False) -> float:
    """Check that a number option is finite (and > 0 when ``positive``).

    Raises:
        typer.BadParameter: naming ``option``.
    """
    if not math.isfinite(value) or (positive and value <= 0):
        need = "a positive number" if positive else "a finite number"
        raise typer.BadParameter(f"must be {need}, got {value}", param_hint=option)
    return value


def image_size(text: str, option: str, minimum: int = 8) -> tuple[int, int]:
    """Parse ``HxW`` (pixels), each side at least ``minimum``.

    Raises:
        typer.BadParameter: naming ``option``.
    """
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"must look like 480x640, got {text!r}",
                                 param_hint=option) from None
    if height < minimum or width < minimum:
        raise typer.BadParameter(f"each side must be at least {minimum} pixels, got {text!r}",
                                 param_hint=option)
    return height, width
