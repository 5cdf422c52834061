"""The estimator's argument checks, each defined once and done at the boundary.

:func:`check_backend_options` is called by the estimator, ``load_estimator`` and the
CLI's model options; :func:`batch_arguments` and :func:`check_calibration` by
``DepthEstimator.predict`` / ``prepare`` before any work. Wrong types are refused with a
hint of what to pass (a path names the reader, a torch tensor the conversion).
"""

from __future__ import annotations

import numbers
import os
import re
from typing import Any

import numpy as np

from deltar.camera import check_image
from deltar.sensor.zone_frame import ZoneFrame

#: Torch precisions the PyTorch backend runs in.
PRECISIONS = ("float32", "float16", "bfloat16")


def check_backend_options(precision: str, flip_average: bool, onnx: bool, *,
                          names: tuple[str, str] = ("precision", "flip_average")) -> None:
    """The backend options' checks, defined once for the estimator, ``load_estimator``
    and the CLI (which name the options ``names``: precision's, flip averaging's).

    Raises:
        ValueError: an unknown precision, or float16 / bfloat16 or flip averaging with
            the onnxruntime backend (``onnx``); naming the option.
    """
    precision_name, flip_name = names
    if precision not in PRECISIONS:
        raise ValueError(f"{precision_name} must be one of {', '.join(PRECISIONS)}, got "
                         f"{precision!r}")
    if onnx and precision != "float32":
        raise ValueError(f"{precision_name}: the onnxruntime backend runs in float32 only")
    if onnx and flip_average:
        # An ONNX file is exported for one zone layout; the mirrored one differs.
        raise ValueError(f"{flip_name} needs a PyTorch model (an ONNX file is fixed to one "
                         "zone layout)")


#: The device names the PyTorch backend takes (``cpu``, ``cuda``, ``cuda:N``, ``mps``).
DEVICE_NAME = re.compile(r"(cpu|mps|cuda)(:\d+)?")


def check_device(name: Any, option: str = "device") -> str:
    """Check that PyTorch can run on device ``name`` here (``cpu``, ``cuda``, ``cuda:N``,
    ``mps``), naming ``option`` in the message; PyTorch must be installed for any but
    ``cpu`` (the caller says which extra).

    Raises:
        ValueError: an unknown device, or a GPU this machine does not have.
    """
    if type(name).__name__ == "device":  # a torch.device: its text form
        name = str(name)
    if not isinstance(name, str) or not DEVICE_NAME.fullmatch(name):
        raise ValueError(f"{option}: unknown device {name!r}; use cpu, cuda, cuda:N or mps")
    if name == "cpu":
        return name
    import torch

    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            cpu = f"{option} cpu" if option.startswith("-") else f"{option}='cpu'"
            raise ValueError(f"{option} {name!r}: no CUDA GPU is available on this machine "
                             f"(use {cpu})")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"{option} {name!r}: this machine has "
                             f"{torch.cuda.device_count()} CUDA GPU(s)")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{option} {name!r}: Apple MPS is not available here")
    return name


_IMAGE_EXPECTED = "image must be an (H, W, 3) uint8 RGB array (or a list of them)"
_ZONE_READER = "deltar.io.zone_file.load_zone_frame"


class InputSizeError(ValueError):
    """A fixed network input size an ONNX model was not exported at (the command line
    says it as its ``--size`` option)."""


def resolve_input_size(input_size: Any, onnx_model: Any) -> tuple[int, int] | None:
    """The estimator's fixed network input size (h, w) pixels, checked: as given, or an
    ONNX model's one exported size; None lets the size rule choose.

    Raises:
        ValueError: a bad size; :class:`InputSizeError` for one the ONNX model was not
            exported at.
    """
    from deltar.inference.preprocess import check_input_size

    if onnx_model is not None:
        sizes = onnx_model.input_sizes
        if input_size is not None and tuple(input_size) not in sizes:
            from deltar.extras import pytorch_remedy

            raise InputSizeError(f"input_size {tuple(input_size)} is not one the ONNX model "
                                 f"{onnx_model.path} was exported at: "
                                 f"{', '.join(map(str, sizes))}; without a fixed size each "
                                 f"image runs at the exported size nearest its aspect, or "
                                 f"{pytorch_remedy('runs any size')}")
        if len(sizes) == 1:
            input_size = sizes[0]
    return None if input_size is None else check_input_size(input_size, "input_size")


def check_fov_deg(fov_deg: Any) -> tuple[float, float]:
    """``fov_deg`` as (horizontal, vertical) degrees, each in (0, 180).

    Raises:
        ValueError: ``"fov_deg must be two angles in (0, 180) degrees, got ..."`` for a
            single number, another count, non-numbers or angles out of range.
    """
    values = fov_deg.tolist() if isinstance(fov_deg, np.ndarray) else fov_deg
    if not isinstance(values, tuple | list) or len(values) != 2 or not all(
            isinstance(v, numbers.Real) and not isinstance(v, bool | np.bool_) and 0 < v < 180
            for v in values):
        raise ValueError(f"fov_deg must be two angles in (0, 180) degrees, "
                         f"(horizontal, vertical), got {fov_deg!r}")
    return float(values[0]), float(values[1])


def describe_argument(value: Any,
                      reader: str = "deltar.data.rgbd_files.read_color") -> str:
    """A short description of a wrongly typed argument, with a hint where one helps
    (``reader``: what reads a path given for it)."""
    kind = type(value).__name__
    if isinstance(value, (str, os.PathLike)):
        return f"a {kind} path {str(value)!r}; read the file first, e.g. with {reader}"
    if type(value).__module__.startswith("torch"):
        return (f"a torch {kind} of shape {tuple(getattr(value, 'shape', ()))}; convert "
                "it with tensor.cpu().numpy() (uint8 RGB, channels last)")
    return f"a {kind}"


def batch_arguments(image: Any, zone_frame: Any
                    ) -> tuple[bool, list[np.ndarray], list[ZoneFrame]]:
    """(single, images, frames) from ``predict``'s arguments, refusing wrong types.

    Args:
        image: an (H, W, 3) image array, or a list of them (a 4-D array is a batch).
        zone_frame: a ``ZoneFrame``, or a list of them for a batch.

    Returns:
        ``single`` (one image given, not a list), the images as a list and the frames
        as a list (their contents are checked by ``DepthEstimator.prepare``).

    Raises:
        ValueError: an argument of the wrong type, naming it and what to pass.
    """
    if isinstance(image, np.ndarray):
        if image.ndim not in (3, 4):
            raise ValueError(f"{_IMAGE_EXPECTED}, got an array of shape {image.shape}")
        single = image.ndim == 3
    elif isinstance(image, (list, tuple)):
        single = False
    else:
        raise ValueError(f"{_IMAGE_EXPECTED}, got {describe_argument(image)}")
    images = [image] if single else list(image)
    if single:
        if not isinstance(zone_frame, ZoneFrame):
            raise ValueError("zone_frame must be a ZoneFrame (e.g. from "
                             "deltar.io.zone_file.load_zone_frame), got "
                             f"{describe_argument(zone_frame, _ZONE_READER)}")
        _revalidated(zone_frame, "zone_frame")
        return True, images, [zone_frame]
    if not isinstance(zone_frame, (list, tuple)):
        raise ValueError(f"for a batch of {len(images)} images, zone_frame must be a list of "
                         f"ZoneFrame, got {describe_argument(zone_frame, _ZONE_READER)}")
    for index, frame in enumerate(zone_frame):
        if isinstance(frame, ZoneFrame):
            _revalidated(frame, f"zone_frame[{index}]")
    return False, images, list(zone_frame)


def _revalidated(frame: ZoneFrame, name: str) -> None:
    """A frame's fields checked again (they may have been reassigned since it was made),
    naming ``name``."""
    try:
        frame.validate()
    except (ValueError, TypeError, AttributeError) as err:
        raise ValueError(f"{name}: {err}") from err


def check_calibration(calibration: Any) -> None:
    """Refuse a ``calibration`` that is neither a ``RigCalibration`` nor None
    (``ValueError`` naming what was given)."""
    from deltar.calibration.rig import RigCalibration

    if calibration is not None and not isinstance(calibration, RigCalibration):
        raise ValueError("calibration must be a RigCalibration (e.g. RigCalibration.load("
                         f"path)) or None, got "
                         f"{describe_argument(calibration, 'RigCalibration.load')}")


def check_batch_inputs(images: Any, frames: Any, max_range_m: float | None) -> list[np.ndarray]:
    """Check a batch's images and zone frames (``DepthEstimator.prepare``'s arguments).

    Args:
        images: B (H, W, 3) uint8 RGB images, all of one size.
        frames: B zone frames of one grid, each a physically possible reading within
            ``max_range_m`` metres (:meth:`ZoneFrame.physical_error`; None: each frame's
            sensor range).

    Returns:
        The B images as checked arrays (:func:`deltar.camera.check_image`).

    Raises:
        ValueError: naming the image or frame (``images[i]`` / ``frames[i]``) and why.
    """
    if len(images) != len(frames) or not images:
        raise ValueError(f"need one zone frame per image, got {len(images)} images and "
                         f"{len(frames)} frames")
    checked = [check_image(img, f"images[{i}]") for i, img in enumerate(images)]
    size = checked[0].shape[:2]
    for i, img in enumerate(checked):
        if img.shape[:2] != size:
            raise ValueError(f"images[{i}] is {img.shape[0]}x{img.shape[1]}, images[0] is "
                             f"{size[0]}x{size[1]}; a batch needs one image size")
    for i, frame in enumerate(frames):
        if not isinstance(frame, ZoneFrame):
            raise ValueError(f"frames[{i}] must be a ZoneFrame, got {type(frame).__name__}")
        if frame.grid != frames[0].grid:
            raise ValueError(f"frames[{i}] has a {frame.grid}x{frame.grid} grid, frames[0] "
                             f"{frames[0].grid}x{frames[0].grid}")
        problem = frame.physical_error(max_range_m)
        if problem is not None:
            raise ValueError(f"frames[{i}]: {problem}")
    return checked
