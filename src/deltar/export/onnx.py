"""Export DeltarNet to ONNX: ``export_onnx`` (run the files with ``OnnxDepthModel``).

The exported graph has a dynamic batch axis and a fixed input size: the network input
size of the camera image size by the one size rule
(:func:`deltar.inference.preprocess.network_input_size`, as ``DepthEstimator`` runs the
model). Parts of the zone fusion take their shapes from the zone layout (tokens per
zone patch, the longest zone window), so the export fixes them too: an ONNX model
serves every zone layout with the same *layout signature* (same patch sizes, windows no
longer than at export). The signature is stored in the model's metadata and checked
before every run (:class:`~deltar.inference.onnx_runtime.OnnxDepthModel`), so a layout
that does not fit raises a clear error instead of giving wrong depth. The nominal
geometry at a fixed image size always fits.

The network is traced on its own traceable path
(:meth:`~deltar.models.DeltarNet.set_traceable`: same outputs, operators the tracer
records); nothing is patched here.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.inference.onnx_runtime import (
    INPUT_NAMES,
    NO_TARGET_INPUT,
    OUTPUT_NAMES,
    SIGNATURE_KEY,
    OnnxDepthModel,
    layout_signature,
    signature_fits,
)

if TYPE_CHECKING:
    import torch

    from deltar.models import DeltarNet

OPSET = 17
#: Old private names, kept for callers: the runtime side lives in
#: :mod:`deltar.inference.onnx_runtime`.
_SIGNATURE_KEY = SIGNATURE_KEY
_signature_fits = signature_fits

__all__ = ["INPUT_NAMES", "OPSET", "OUTPUT_NAMES", "OnnxDepthModel", "example_inputs",
           "export_input_size", "export_onnx", "layout_signature"]


def _tuple_outputs(model: DeltarNet) -> torch.nn.Module:
    """Wrap DeltarNet so the traced graph returns (depth, bin_edges, uncertainty)."""
    import torch

    class TupleOutputs(torch.nn.Module):
        def __init__(self, inner: DeltarNet) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, image, hypotheses, zone_rects, zone_valid, zone_no_target=None):
            out = self.inner(image, hypotheses, zone_rects, zone_valid,
                             zone_no_target=zone_no_target)
            return out["depth"], out["bin_edges"], out["uncertainty"]

    return TupleOutputs(model).eval()


def export_input_size(model: DeltarNet, height: int, width: int) -> tuple[int, int]:
    """The fixed (H, W) network input, pixels, of an export for ``height`` x ``width`` images.

    The one size rule (:func:`~deltar.inference.preprocess.network_input_size`) with the
    model's design size: the size ``DepthEstimator`` runs the model at for such images.
    """
    from deltar.inference.preprocess import network_input_size

    return network_input_size(height, width, design_size=model.config.get("design_size"))


def example_inputs(model: DeltarNet, height: int, width: int,
                   zone_rects: np.ndarray | None = None,
                   grid: int = 8) -> tuple[torch.Tensor, ...]:
    """Batch-1 network inputs for images of ``height`` x ``width``, as the estimator makes.

    The network input size is :func:`export_input_size` (the one size rule), and the
    zone layout is mapped to it with :func:`~deltar.inference.preprocess.scale_rects`,
    exactly as ``DepthEstimator`` does.

    Args:
        model: the network (its ``num_hypotheses`` and ``design_size``).
        height, width: camera image size in pixels.
        zone_rects: (Z, 4) layout in image pixels; the nominal geometry when None.
        grid: zones per side for the nominal layout.

    Returns:
        (image (1, 3, h, w) mid-grey, hypotheses (1, Z, K) around 2 m, zone_rects
        (1, Z, 4) in network-input pixels, zone_valid (1, Z) all True), and
        zone_no_target (1, Z) all False for a network whose head uses the flags.
    """
    import torch

    from deltar.inference.preprocess import scale_rects
    from deltar.sensor.placement import nominal_zone_rects
    from deltar.sensor.zone_frame import ZoneFrame

    frame = ZoneFrame(mean_m=np.full((grid, grid), 2.0), sigma_m=np.full((grid, grid), 0.05),
                      valid=np.ones((grid, grid), bool))
    rects = nominal_zone_rects(frame, height, width) if zone_rects is None else zone_rects
    net_height, net_width = export_input_size(model, height, width)
    rects = scale_rects(np.asarray(rects, dtype=np.float32), (height, width),
                        (net_height, net_width))
    zones = rects.shape[0]
    k = int(model.config["num_hypotheses"])
    hypotheses = torch.linspace(1.8, 2.2, k).expand(1, zones, k).contiguous()
    inputs = (torch.zeros(1, 3, net_height, net_width), hypotheses,
              torch.from_numpy(rects)[None], torch.ones(1, zones, dtype=torch.bool))
    if getattr(model, "uses_no_target", False):
        # The head reads the flags: the export takes them as a fifth input.
        inputs += (torch.zeros(1, zones, dtype=torch.bool),)
    return inputs


def export_onnx(model: DeltarNet, path: str | os.PathLike, height: int, width: int, *,
                zone_rects: np.ndarray | None = None, overwrite: bool = False,
                metadata: dict[str, str] | None = None) -> Path:
    """Export ``model`` to an ONNX file with a dynamic batch axis, atomically.

    Args:
        model: the network (any preset); exported in eval mode, float32, on the CPU.
        path: destination ``.onnx`` file.
        height, width: camera image size in pixels; the model's fixed input size is
            :func:`export_input_size` of it (the one size rule, as ``DepthEstimator``
            runs the model; stored as ``deltar_input_size`` metadata beside the camera
            size ``deltar_image_size``).
        zone_rects: (Z, 4) zone layout in image pixels that fixes the layout signature;
            the nominal 8x8 geometry at this size when None.
        overwrite: replace an existing file (default: ``FileExistsError``).
        metadata: extra string key/values stored in the model (e.g. the preset).

    Returns:
        The written path.
    """
    import onnx
    import torch

    from deltar.io.atomic import atomic_path

    if height < 1 or width < 1:
        raise ValueError(f"height and width must be positive, got {height}x{width}")
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"refusing to overwrite existing file: {path}")
    model = model.eval().float().cpu()
    inputs = example_inputs(model, height, width, zone_rects)
    grid = round(inputs[2].shape[1] ** 0.5)
    # Only the zone-patch fusion bakes the layout's shape into the graph; a network
    # without it (e.g. the plane-select one) takes any layout, which an empty signature
    # records.
    uses_patches = getattr(model, "distribution_encoder", None) is not None
    signature = layout_signature(inputs[2].numpy(), grid) if uses_patches else []
    input_names = [*INPUT_NAMES, *((NO_TARGET_INPUT,) if len(inputs) > 4 else ())]
    dynamic = {name: {0: "batch"} for name in (*input_names, *OUTPUT_NAMES)}
    net_height, net_width = inputs[0].shape[-2:]
    with atomic_path(path, overwrite=overwrite) as tmp, _traceable(model), \
            torch.no_grad(), _quiet_tracer():
        torch.onnx.export(_tuple_outputs(model), inputs, str(tmp), input_names=input_names,
                          output_names=list(OUTPUT_NAMES), dynamic_axes=dynamic,
                          opset_version=OPSET, dynamo=False)
        proto = onnx.load(str(tmp))
        extra = {SIGNATURE_KEY: json.dumps(signature), "deltar_grid": str(grid),
                 "deltar_image_size": f"{height}x{width}",
                 "deltar_input_size": f"{net_height}x{net_width}",
                 "deltar_config": json.dumps(model.config, default=list),
                 **(metadata or {})}
        for key, value in extra.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, str(value)
        onnx.save(proto, str(tmp))
    return path


@contextlib.contextmanager
def _traceable(model: DeltarNet) -> Iterator[None]:
    """The model on its traceable path for the export, then back as it was."""
    previous = model.traceable
    model.set_traceable(True)
    try:
        yield
    finally:
        model.set_traceable(previous)


@contextlib.contextmanager
def _quiet_tracer() -> Iterator[None]:
    # The tracer warns about every Python-side shape computation, which is expected
    # here (the layout signature is fixed on purpose and checked at run time).
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield
