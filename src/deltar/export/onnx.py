"""Export DeltarNet to ONNX and run the exported model with onnxruntime.

The exported graph has a dynamic batch axis and a fixed input size. Parts of the
zone fusion take their shapes from the zone layout (tokens per zone patch, the
longest zone window), so the export fixes them too: an ONNX model serves every zone
layout with the same *layout signature* (same patch sizes, windows no longer than
at export). The signature is stored in the model's metadata and checked before
every run, so a layout that does not fit raises a clear error instead of giving
wrong depth. The nominal geometry at a fixed image size always fits.

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

if TYPE_CHECKING:
    import torch

    from deltar.models import DeltarNet

INPUT_NAMES = ("image", "hypotheses", "zone_rects", "zone_valid")
OUTPUT_NAMES = ("depth", "bin_edges", "uncertainty")
OPSET = 17
_SIGNATURE_KEY = "deltar_layout_signature"


def layout_signature(zone_rects: np.ndarray | torch.Tensor, grid: int) -> list[dict]:
    """The shape-determining numbers of a zone layout at each fusion stride.

    Args:
        zone_rects: (B, Z, 4) rectangles in network-input pixels.
        grid: zones per side.

    Returns:
        One dict per fusion stride: ``stride``, ``patch`` [p_h, p_w] tokens per zone,
        ``max_length`` [rows, cols] of the longest zone window in feature cells.
    """
    import torch

    from deltar.models.decoder import FUSION_STRIDES
    from deltar.models.zone_patches import zone_window

    rects = torch.as_tensor(np.asarray(zone_rects, dtype=np.float32))
    out = []
    for stride in FUSION_STRIDES:
        window = zone_window(rects, float(stride), grid)
        out.append({"stride": int(stride), "patch": [int(p) for p in window.patch],
                    "max_length": [int(v) for v in window.length.amax(0).tolist()]})
    return out


def _signature_fits(signature: list[dict], exported: list[dict]) -> bool:
    return all(s["patch"] == e["patch"] and s["max_length"][0] <= e["max_length"][0]
               and s["max_length"][1] <= e["max_length"][1]
               for s, e in zip(signature, exported, strict=True))


@contextlib.contextmanager
def _traceable(model: DeltarNet) -> Iterator[None]:
    """The model on its traceable path for the export, then back as it was."""
    previous = model.traceable
    model.set_traceable(True)
    try:
        yield
    finally:
        model.set_traceable(previous)


def _tuple_outputs(model: DeltarNet) -> torch.nn.Module:
    """Wrap DeltarNet so the traced graph returns (depth, bin_edges, uncertainty)."""
    import torch

    class TupleOutputs(torch.nn.Module):
        def __init__(self, inner: DeltarNet) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, image, hypotheses, zone_rects, zone_valid):
            out = self.inner(image, hypotheses, zone_rects, zone_valid)
            return out["depth"], out["bin_edges"], out["uncertainty"]

    return TupleOutputs(model).eval()


def example_inputs(model: DeltarNet, height: int, width: int,
                   zone_rects: np.ndarray | None = None,
                   grid: int = 8) -> tuple[torch.Tensor, ...]:
    """Batch-1 network inputs for images of ``height`` x ``width``, as the estimator makes.

    The network input size is :func:`~deltar.inference.estimator.network_size` of the
    image size (with the model's design size), and the zone layout is mapped to it with
    :func:`~deltar.inference.estimator.scale_rects`, exactly as ``DepthEstimator`` does.

    Args:
        model: the network (its ``num_hypotheses``).
        height, width: camera image size in pixels.
        zone_rects: (Z, 4) layout in image pixels; the nominal geometry when None.
        grid: zones per side for the nominal layout.

    Returns:
        (image (1, 3, h, w) mid-grey, hypotheses (1, Z, K) around 2 m, zone_rects
        (1, Z, 4) in network-input pixels, zone_valid (1, Z) all True).
    """
    import torch

    from deltar.inference.estimator import network_size, nominal_zone_rects, scale_rects
    from deltar.sensor.zone_frame import ZoneFrame

    frame = ZoneFrame(mean_m=np.full((grid, grid), 2.0), sigma_m=np.full((grid, grid), 0.05),
                      valid=np.ones((grid, grid), bool))
    rects = nominal_zone_rects(frame, height, width) if zone_rects is None else zone_rects
    net_height, net_width = network_size(height, width,
                                         design_size=model.config.get("design_size"))
    rects = scale_rects(np.asarray(rects, dtype=np.float32), (height, width),
                        (net_height, net_width))
    zones = rects.shape[0]
    k = int(model.config["num_hypotheses"])
    hypotheses = torch.linspace(1.8, 2.2, k).expand(1, zones, k).contiguous()
    return (torch.zeros(1, 3, net_height, net_width), hypotheses,
            torch.from_numpy(rects)[None], torch.ones(1, zones, dtype=torch.bool))


def export_onnx(model: DeltarNet, path: str | os.PathLike, height: int, width: int, *,
                zone_rects: np.ndarray | None = None, overwrite: bool = False,
                metadata: dict[str, str] | None = None) -> Path:
    """Export ``model`` to an ONNX file with a dynamic batch axis, atomically.

    Args:
        model: the network (any preset); exported in eval mode, float32, on the CPU.
        path: destination ``.onnx`` file.
        height, width: camera image size in pixels; the model's fixed input size is
            that size rounded to multiples of 32 (as ``DepthEstimator`` resizes).
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
    signature = layout_signature(inputs[2].numpy(), grid)
    dynamic = {name: {0: "batch"} for name in (*INPUT_NAMES, *OUTPUT_NAMES)}
    with atomic_path(path, overwrite=overwrite) as tmp, _traceable(model), \
            torch.no_grad(), _quiet_tracer():
        torch.onnx.export(_tuple_outputs(model), inputs, str(tmp), input_names=list(INPUT_NAMES),
                          output_names=list(OUTPUT_NAMES), dynamic_axes=dynamic,
                          opset_version=OPSET, dynamo=False)
        proto = onnx.load(str(tmp))
        extra = {_SIGNATURE_KEY: json.dumps(signature), "deltar_grid": str(grid),
                 "deltar_image_size": f"{height}x{width}",
                 "deltar_config": json.dumps(model.config, default=list),
                 **(metadata or {})}
        for key, value in extra.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, str(value)
        onnx.save(proto, str(tmp))
    return path


@contextlib.contextmanager
def _quiet_tracer() -> Iterator[None]:
    # The tracer warns about every Python-side shape computation, which is expected
    # here (the layout signature is fixed on purpose and checked at run time).
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


class OnnxDepthModel:
    """An exported DeltarNet run with onnxruntime on the CPU.

    Args:
        path: the ``.onnx`` file written by :func:`export_onnx`.
        num_threads: onnxruntime intra-op threads (its default when None).
        allow_spinning: let onnxruntime's idle worker threads busy-wait for the next
            run (its default). Off by default here: between runs the pipeline's own
            work (decoding, resizing) needs those cores.

    Attributes:
        input_size: (H, W) fixed input size in pixels.
        num_hypotheses: K hypotheses per zone.
        grid: zones per side.
        contract: the exported network's config (``deltar_config`` metadata): its input
            contract (``image_mean``, ``image_std``, ``hypothesis_sampling``,
            ``num_hypotheses``, ...); files without it get the release's ImageNet
            normalisation and inverse-CDF sampling.
    """

    def __init__(self, path: str | os.PathLike, num_threads: int | None = None,
                 allow_spinning: bool = False) -> None:
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model not found: {path}")
        options = ort.SessionOptions()
        if num_threads:
            options.intra_op_num_threads = int(num_threads)
            options.inter_op_num_threads = 1
        if not allow_spinning:
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(path), options,
                                                providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types
            raise ValueError(f"{path}: cannot load ONNX model: {err}") from err
        self.path = path
        names = [i.name for i in self.session.get_inputs()]
        if names != list(INPUT_NAMES):
            raise ValueError(f"{path}: inputs are {names}, expected {list(INPUT_NAMES)} "
                             "(export with deltar export)")
        meta = self.session.get_modelmeta().custom_metadata_map
        if _SIGNATURE_KEY not in meta:
            raise ValueError(f"{path}: no {_SIGNATURE_KEY} metadata (export with deltar export)")
        self.signature = json.loads(meta[_SIGNATURE_KEY])
        self.grid = int(meta["deltar_grid"])
        self.metadata = dict(meta)
        shapes = {i.name: i.shape for i in self.session.get_inputs()}
        self.input_size = (int(shapes["image"][2]), int(shapes["image"][3]))
        self.num_hypotheses = int(shapes["hypotheses"][2])
        try:
            config = json.loads(meta.get("deltar_config", "{}"))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: unreadable deltar_config metadata: {err}") from err
        self.contract = {**config, "num_hypotheses": self.num_hypotheses}

    def check_layout(self, zone_rects: np.ndarray) -> None:
        """Raise ``ValueError`` if a (B, Z, 4) layout does not fit the exported one."""
        rects = np.asarray(zone_rects, dtype=np.float32)
        if rects.ndim != 3 or rects.shape[1] != self.grid * self.grid or rects.shape[2] != 4:
            raise ValueError(f"zone_rects must be (B, {self.grid * self.grid}, 4), got "
                             f"{rects.shape}")
        signature = layout_signature(rects, self.grid)
        if not _signature_fits(signature, self.signature):
            raise ValueError(f"{self.path}: this zone layout {signature} does not fit the one "
                             f"the model was exported for {self.signature}; re-export with "
                             "this layout (deltar export --layout-from) or use the PyTorch "
                             "backend")

    def run(self, image: np.ndarray, hypotheses: np.ndarray, zone_rects: np.ndarray,
            zone_valid: np.ndarray) -> dict[str, np.ndarray]:
        """Run the network; same inputs and outputs as ``DeltarNet.forward`` (numpy).

        Args:
            image: (B, 3, H, W) float32 normalised, H x W = :attr:`input_size`.
            hypotheses: (B, Z, K) float32 metres.
            zone_rects: (B, Z, 4) float32 pixels of the input.
            zone_valid: (B, Z) bool.

        Returns:
            dict of ``depth`` (B, 1, H/2, W/2), ``bin_edges`` (B, N + 1) and
            ``uncertainty`` (B, 1, H/2, W/2), float32 metres.
        """
        image = np.asarray(image, dtype=np.float32)
        if image.ndim != 4 or tuple(image.shape[1:]) != (3, *self.input_size):
            raise ValueError(f"image must be (B, 3, {self.input_size[0]}, "
                             f"{self.input_size[1]}), got {image.shape}")
        hyp = np.asarray(hypotheses, dtype=np.float32)
        if hyp.ndim != 3 or hyp.shape[2] != self.num_hypotheses or not np.all(np.isfinite(hyp)):
            raise ValueError(f"hypotheses must be finite (B, Z, {self.num_hypotheses}), got "
                             f"{hyp.shape}")
        self.check_layout(zone_rects)
        feeds = {"image": image, "hypotheses": hyp,
                 "zone_rects": np.asarray(zone_rects, dtype=np.float32),
                 "zone_valid": np.asarray(zone_valid, dtype=bool)}
        outputs = self.session.run(list(OUTPUT_NAMES), feeds)
        return dict(zip(OUTPUT_NAMES, outputs, strict=True))
