"""Models shipped inside the package (no download needed).

``default`` is a ``deltar-select`` network (frozen ImageNet EfficientNet-Lite0
descriptors choosing among the zones' local planes) trained on CPU on real indoor RGB-D
frames with simulated L5 zones (docs/training.md: the recipe and its leave-one-scene-out
tables).

Each bundled model is shipped twice: the checkpoint (``.pt``, the PyTorch path) and its
ONNX export, which the estimator runs through onnxruntime when PyTorch is not installed
(:func:`bundled_onnx`; tests keep the two equal). The export is one fixed-size file per
common camera aspect (4:3, 16:9, 16:10 and 3:2, 1:1, and the portrait 3:4 and 9:16:
network inputs 256x320, 224x384, 224x352, 288x288, 320x256, 384x224), all reading one
shared weights file (``.onnx.data``), written from the checkpoint with the checkpoint's
config as metadata by (one command)::

    deltar export --checkpoint default --out src/deltar/weights/deltar_select_default.onnx
        --size 480x640,720x1280,800x1280,480x480,640x480,1280x720

:func:`bundled_onnx` gives the 4:3 file, which lists the others; an image runs at the
size the size rule gives it, as on the PyTorch path.
"""

from __future__ import annotations

from pathlib import Path

_HERE = Path(__file__).resolve().parent

#: Bundled model name -> file inside this package.
BUNDLED_MODELS: dict[str, str] = {"default": "deltar_select_default.pt"}
#: Bundled model name -> its ONNX export inside this package.
BUNDLED_ONNX: dict[str, str] = {"default": "deltar_select_default.onnx"}
#: The camera image sizes (H, W) pixels the bundled ONNX files were exported for, the
#: first that of the file :func:`bundled_onnx` gives (a 4:3 camera: network input 256x320
#: by the size rule).
BUNDLED_ONNX_EXPORT_SIZES = ((480, 640), (720, 1280), (800, 1280), (480, 480), (640, 480),
                            (1280, 720))
BUNDLED_ONNX_EXPORT_SIZE = BUNDLED_ONNX_EXPORT_SIZES[0]


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
