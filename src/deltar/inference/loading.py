"""Load a depth estimator from one name or file: :func:`load_estimator`.

The one factory of estimators (as timm's ``create_model``): the Python API, every
``deltar`` command that runs a model (``predict``, ``replay``, ``wall-test``, ``export``)
and the ``evaluate`` methods load through it. It loads the weights and builds a
:class:`~deltar.inference.estimator.DepthEstimator` around them; the estimator's own
constructor takes a model object already in hand.

A model source is one of (``kind``):

- ``"bundled"``: a model shipped with the package, by name (``"default"``, see
  :mod:`deltar.weights`); ``source=None`` means the bundled ``"default"``;
- ``"checkpoint"``: a deltar checkpoint file (``.pt``: a training run's ``model.pt`` or
  a packaged model; see :mod:`deltar.models.checkpoint`), or a bundled name;
- ``"official"``: the officially released DELTAR weights (e.g. ``nyu.pt``);
- ``"onnx"``: an ONNX file written by ``deltar export`` (onnxruntime, CPU, float32), or
  a bundled model's name for its shipped export (also where PyTorch is installed; an
  existing file of that name wins);
- ``"preset"``: a :func:`~deltar.models.create_model` preset with RANDOM weights
  (pipeline tests and timing only; a ``UserWarning`` says so).

Without ``kind`` the source is told apart in this order: None or a bundled name, an
existing ``.onnx`` file, another existing file (a checkpoint), a preset name. Official
weights are files too, so they need ``kind="official"``.

Backends: a bundled model runs in PyTorch when PyTorch is installed (the ``torch``
extra), else from its shipped ONNX export through onnxruntime (the base install; the
same depth within 1e-4 m, tested). Checkpoints, official weights and presets need
PyTorch; without it they raise ``ModuleNotFoundError`` naming the extra.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from deltar.contract import PRESET_NAMES
from deltar.extras import require_torch, torch_available
from deltar.inference.checks import check_backend_options, check_device
from deltar.inference.estimator import DepthEstimator
from deltar.inference.preprocess import check_input_size
from deltar.io.input_file import input_file
from deltar.io.resources import check_threads
from deltar.weights import (
    BUNDLED_MODELS,
    BUNDLED_ONNX,
    bundled_model_names,
    bundled_onnx,
    resolve_checkpoint,
)

if TYPE_CHECKING:
    from deltar.models import DeltarNet

#: The kinds of model source :func:`load_estimator` accepts.
MODEL_SOURCE_KINDS = ("bundled", "checkpoint", "official", "onnx", "preset")
#: The bundled model used when no source is given.
DEFAULT_MODEL = "default"


def resolve_source(source: str | os.PathLike | None = None, kind: str | None = None
                   ) -> tuple[str, str]:
    """The kind and the name or path of a model source, loading nothing.

    Args:
        source: a bundled name, a file path or a preset name; None: the bundled default.
        kind: one of :data:`MODEL_SOURCE_KINDS`, or None to tell it from ``source``.

    Returns:
        ``(kind, source)`` with ``source`` as text (a path or a name).

    Raises:
        TypeError: a source that is neither text nor a path.
        ValueError: an empty source, an unknown ``kind``, or ``kind`` given without a
            source (other than ``"bundled"``), a Lightning ``.ckpt`` (package it first), or
            ``kind="preset"`` with a name that is none (:data:`deltar.contract.PRESET_NAMES`).
        FileNotFoundError: no bundled model in this installation for ``source=None``, or
            a source that is neither a bundled model, an existing file nor a preset.
    """
    if kind is not None and kind not in MODEL_SOURCE_KINDS:
        raise ValueError(f"kind must be one of {', '.join(MODEL_SOURCE_KINDS)}, got {kind!r}")
    if source is None:
        if kind not in (None, "bundled"):
            raise ValueError(f"kind={kind!r} needs a source (a file or a name)")
        if DEFAULT_MODEL not in bundled_model_names():
            raise FileNotFoundError("this installation has no bundled model; give a "
                                    "checkpoint, official weights, an ONNX file or a preset")
        return "bundled", DEFAULT_MODEL
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source must be a model name or a file path (str or path), got "
                        f"{type(source).__name__} {source!r}")
    text = os.fspath(source)
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"source must name a model or a file, got {text!r}")
    if Path(text).suffix.lower() == ".ckpt" and kind in (None, "checkpoint"):
        raise ValueError(f"{text} is a Lightning training checkpoint; use the run's model.pt "
                         "or package it (deltar.training.package.package_checkpoint)")
    if kind == "preset" and text not in PRESET_NAMES:
        raise ValueError(f"unknown model preset {text!r}; known presets: "
                         f"{', '.join(PRESET_NAMES)}")
    if kind is not None:
        return kind, text
    if text in BUNDLED_MODELS:
        return "bundled", text
    path = Path(text)
    if path.exists():  # a folder or a device is refused by the file's reader, by name
        return ("onnx" if path.suffix.lower() == ".onnx" else "checkpoint"), text
    if text in PRESET_NAMES:
        return "preset", text
    raise FileNotFoundError(f"model {text!r} is not a bundled model "
                            f"({', '.join(BUNDLED_MODELS)}), an existing file or a preset "
                            f"({', '.join(PRESET_NAMES)})")


def load_estimator(source: str | os.PathLike | None = None, *, kind: str | None = None,
                   device: str = "cpu", precision: str = "float32",
                   input_size: tuple[int, int] | None = None, threads: int | None = None,
                   flip_average: bool = False, **estimator_kwargs: Any) -> DepthEstimator:
    """A :class:`~deltar.inference.estimator.DepthEstimator` from any model source.

    Args:
        source: a bundled model name, a checkpoint / official-weights / ONNX file, or a
            preset name; None: the bundled ``"default"`` model (see the module docstring).
        kind: one of :data:`MODEL_SOURCE_KINDS`; None tells it from ``source``.
        device: torch device of the PyTorch backends (``"cpu"``, ``"cuda"``, ...); the
            ONNX backend always runs on the CPU.
        precision: ``"float32"``, ``"float16"`` or ``"bfloat16"`` (PyTorch backends; ONNX
            runs in float32 only).
        input_size: fixed network input (height, width) in pixels, multiples of 32; None:
            each image by the one size rule (its aspect kept at the weights' design pixel
            count, :func:`~deltar.inference.preprocess.network_input_size`).
        threads: CPU threads; sets torch's thread count for the process and the
            onnxruntime session's. None leaves both at their defaults.
        flip_average: test-time flip averaging (PyTorch backends only).
        estimator_kwargs: further :class:`DepthEstimator` arguments (``intrinsics``,
            ``fov_deg``, ``sampling``, ``max_range_m``, ...).

    Returns:
        The estimator, ready for ``predict``; ``estimator.weights`` says what was loaded.

    Raises:
        ValueError: bad arguments (unknown kind or precision, a size not a multiple of
            32, flip averaging with ONNX) or weights that do not load; messages name the
            argument or file.
        FileNotFoundError: a missing file or an unknown name.
        ModuleNotFoundError: PyTorch is not installed and the source or an option needs
            it (a checkpoint, official weights, a preset; a device other than the CPU,
            float16 / bfloat16 or flip averaging); the message names the ``torch`` extra.
    """
    kind, text = resolve_source(source, kind)
    if kind in ("bundled", "checkpoint") and text in BUNDLED_MODELS and not torch_available():
        # Without PyTorch a bundled model runs from its ONNX export (same depth).
        kind, text = "onnx", _bundled_onnx_path(text, device, precision, flip_average)
    elif kind == "onnx" and text in BUNDLED_ONNX and not Path(text).exists():
        # Asked for by name (no file of that name here): the shipped export.
        path = bundled_onnx(text)
        if path is None:
            raise FileNotFoundError(f"this installation has no ONNX export of the bundled "
                                    f"model {text!r}")
        text = str(path)
    check_backend_options(precision, flip_average, kind == "onnx")
    if str(device) != "cpu" and torch_available():
        check_device(device)  # torch's own errors name no argument
    checkpoint = None
    if kind != "onnx":
        # A file that is not there is said before PyTorch is asked for: installing the
        # extra would not help.
        if kind == "bundled" and text not in BUNDLED_MODELS:
            raise FileNotFoundError(f"no bundled model {text!r}; bundled: "
                                    f"{', '.join(BUNDLED_MODELS)}")
        if kind in ("bundled", "checkpoint"):
            checkpoint = resolve_checkpoint(text)
            if text not in BUNDLED_MODELS:
                input_file(checkpoint, "checkpoint")
        elif kind == "official":
            input_file(Path(text), "official weights")
        require_torch(f"the {kind} model {text!r}")
    if input_size is not None:
        input_size = check_input_size(input_size, "input_size")
    if threads is not None:
        threads = check_threads(threads, "threads")
        if kind != "onnx" or torch_available():
            import torch

            torch.set_num_threads(int(threads))
    kwargs: dict[str, Any] = {"input_size": input_size, **estimator_kwargs}
    if flip_average:
        kwargs["flip_average"] = True
    if kind == "onnx":
        from deltar.inference.onnx_runtime import OnnxDepthModel

        onnx_model = OnnxDepthModel(text, num_threads=threads)
        bundled = any(Path(text) == bundled_onnx(name) for name in BUNDLED_ONNX)
        weights = (f"{onnx_model.metadata.get('deltar_weights', text)} (onnxruntime)"
                   if bundled else f"onnx {text}")
        return DepthEstimator(onnx_model=onnx_model, weights=weights, precision=precision,
                              **kwargs)
    kwargs.update(device=device, precision=precision)
    if checkpoint is not None:
        from deltar.models.checkpoint import load_checkpoint

        model, preset, _ = load_checkpoint(checkpoint)
        return DepthEstimator(model, weights=f"{preset} from {text}", **kwargs)
    if kind == "official":  # its outputs resized as the release resizes them
        kwargs.setdefault("output_align_corners", True)
        return DepthEstimator(_official_model(Path(text)), weights=f"deltar-official from {text}",
                              **kwargs)
    from deltar.models import create_model

    warnings.warn(f"preset {text!r} has random, untrained weights: the depth it predicts "
                  "is meaningless", UserWarning, stacklevel=2)
    return DepthEstimator(create_model(text), weights=f"{text} (random weights)", **kwargs)


def _bundled_onnx_path(name: str, device: str, precision: str, flip_average: bool) -> str:
    """The ONNX export of bundled model ``name``, for running it without PyTorch.

    Raises:
        ModuleNotFoundError: naming the ``torch`` extra, for options only the PyTorch
            backend has (a device other than the CPU, float16 / bfloat16, flip
            averaging) or an installation without the ONNX file.
    """
    needs = [what for what, asked in (("device " + repr(device), device != "cpu"),
                                      ("precision " + repr(precision), precision != "float32"),
                                      ("flip averaging", flip_average)) if asked]
    path = bundled_onnx(name)
    if needs or path is None:
        require_torch(f"the bundled model {name!r} with {', '.join(needs)}" if needs else
                      f"the bundled model {name!r} (no ONNX export in this installation)")
    return str(path)


def _official_model(path: Path) -> DeltarNet:
    """The released architecture with the officially released weights (e.g. ``nyu.pt``,
    a file :func:`load_estimator` has checked exists).

    Raises:
        ValueError: the file's weights do not fit the released architecture.
    """
    from deltar.models import create_model, load_official_weights

    model = create_model("deltar-official")
    try:
        report = load_official_weights(model, path)
    except (ValueError, RuntimeError, KeyError) as err:
        raise ValueError(f"{path}: cannot load official weights: {err}") from err
    if not report.ok:
        raise ValueError(f"{path}: official weights did not load cleanly: "
                         f"{report.summary()}")
    return model
