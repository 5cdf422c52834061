"""Models shipped inside the package (no download needed).

``default`` is a ``deltar-select`` network (frozen ImageNet EfficientNet-Lite0
descriptors choosing among the zones' local planes) trained on CPU on real indoor RGB-D
frames with simulated L5 zones (docs/training.md: the recipe and its leave-one-scene-out
tables).

Each bundled model is shipped twice: the checkpoint (``.pt``, the PyTorch path) and its
ONNX export (``.onnx``, written from the checkpoint by ``deltar export --checkpoint
default --size 480x640``, with the checkpoint's config as metadata), which the estimator
runs through onnxruntime when PyTorch is not installed (:func:`bundled_onnx`; a test keeps
the two equal). Its input is fixed at 256x320, the network size of every 4:3 camera.
"""

from __future__ import annotations

from pathlib import Path

_HERE = Path(__file__).resolve().parent

#: Bundled model name -> file inside this package.
BUNDLED_MODELS: dict[str, str] = {"default": "deltar_select_default.pt"}
#: Bundled model name -> its ONNX export inside this package.
BUNDLED_ONNX: dict[str, str] = {"default": "deltar_select_default.onnx"}
#: The camera image size (H, W) pixels the bundled ONNX files were exported for (a 4:3
#: camera: network input 256x320 by the size rule).
BUNDLED_ONNX_EXPORT_SIZE = (480, 640)


def bundled_model_names() -> list[str]:
    """Names of the bundled models whose file is present in this installation."""
    return [name for name, file in BUNDLED_MODELS.items() if (_HERE / file).is_file()]


def resolve_checkpoint(name_or_path: str | Path) -> Path:
    """Path of a checkpoint given a bundled model name (e.g. ``"default"``) or a path.

    Raises:
        FileNotFoundError: neither a bundled model nor an existing path; the message
            lists the bundled names.
    """
    text = str(name_or_path)
    if text in BUNDLED_MODELS:
        path = _HERE / BUNDLED_MODELS[text]
        if not path.is_file():
            raise FileNotFoundError(f"bundled model {text!r} is missing from this "
                                    f"installation ({path})")
        return path
    path = Path(name_or_path)
    if not path.exists():  # a folder or a device is the reader's to tell apart
        raise FileNotFoundError(f"checkpoint {text!r} is neither a bundled model "
                                f"({', '.join(BUNDLED_MODELS)}) nor an existing file")
    return path


def bundled_onnx(name: str) -> Path | None:
    """Path of a bundled model's ONNX export, or None when this installation has none.

    Args:
        name: a bundled model name (a key of :data:`BUNDLED_MODELS`).
    """
    file = BUNDLED_ONNX.get(name)
    if file is None or not (_HERE / file).is_file():
        return None
    return _HERE / file
