"""Static int8 quantisation of an exported ONNX model (onnxruntime, QDQ format).

The convolutions (and, optionally, the matrix products) of the encoder, decoder and
fusion get int8 weights (per output channel) and uint8 activations whose ranges are
calibrated on real frames; the head, which turns features into per-pixel bin
probabilities and depth, stays in float32 (its logits feed exponentials, where int8
steps would show directly as depth steps). The quantised file keeps the float model's
inputs, outputs and deltar metadata, so :class:`~deltar.inference.onnx_runtime.OnnxDepthModel`
and ``load_estimator(path)`` run it like any export.

Calibration frames are RGB-D frames whose zone readings are simulated from their depth
with :func:`~deltar.sensor.simulate_frame.simulate_zone_frame` on the layout the model was
exported for, so the calibrated ranges are those of real images and real zone signals.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.io.input_file import input_file, input_folder

if TYPE_CHECKING:
    from deltar.inference.estimator import DepthEstimator

#: Node-name fragments of the float32 part (the torch exporter names nodes by module).
FLOAT_PARTS = ("/head/",)
#: Metadata key recording how a model was quantised.
QUANT_KEY = "deltar_quantization"


def open_calibration_frames(source: str | os.PathLike) -> Sequence:
    """The RGB-D reader of an ``--int8`` calibration folder, opened without reading a
    frame, so a missing folder or one that is not an RGB-D folder fails before the export.

    Raises:
        FileNotFoundError / ValueError: naming the folder (missing, not a folder, no
            frames, unknown layout).
    """
    from deltar.data.rgbd import open_rgbd

    input_folder(source, "calibration RGB-D folder")
    reader = open_rgbd(source)
    if len(reader) == 0:
        raise ValueError(f"{source}: no RGB-D frames")
    return reader


def calibration_feeds(estimator: DepthEstimator, source: str | os.PathLike | Sequence,
                      frames: int = 16, zone_rects: np.ndarray | None = None,
                      rects_size: tuple[int, int] | None = None
                      ) -> list[dict[str, np.ndarray]]:
    """Network inputs for ``frames`` RGB-D frames spread evenly over ``source``.

    Each frame's zone reading is simulated from its depth (mean, sigma and the
    no-target flags, as a VL53L5CX reports; with CNH histograms too when the weights
    were trained on them, ``estimator.histogram_hypotheses``) on the estimator's zone
    layout for the image, then prepared exactly as ``estimator.predict`` would.

    Args:
        estimator: the estimator of the exported model (its layout and input size).
        source: an RGB-D folder (:func:`~deltar.data.rgbd.open_rgbd`), or its reader
            (:func:`open_calibration_frames`).
        frames: number of frames (>= 1); all of them when the folder has fewer.
        zone_rects: (Z, 4) zone layout in pixels of a ``rects_size`` image (the layout
            a model was exported for); the estimator's nominal layout when None.
        rects_size: (H, W) the ``zone_rects`` refer to; needed with ``zone_rects``.

    Returns:
        One feed dict per frame: ``image`` (1, 3, h, w) float32, ``hypotheses`` (1, Z, K)
        float32 metres, ``zone_rects`` (1, Z, 4) float32 pixels, ``zone_valid`` (1, Z) bool,
        ``zone_no_target`` (1, Z) bool for a file that takes the flags and
        ``zone_targets`` (1, Z, T, 2) float32 for one that reads several targets per
        zone (simulated with that many).
    """
    from deltar.inference.onnx_runtime import INPUT_NAMES, NO_TARGET_INPUT, TARGETS_INPUT
    from deltar.inference.preprocess import scale_rects
    from deltar.sensor.simulate_frame import simulate_zone_frame
    from deltar.sensor.targets import fixed_target_slots
    from deltar.sensor.zone_frame import ZoneFrame

    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    reader = (open_calibration_frames(source) if isinstance(source, (str, os.PathLike))
              else source)
    picks = np.unique(np.linspace(0, len(reader) - 1, min(frames, len(reader))).round())
    grid = estimator.onnx_model.grid if estimator.onnx_model is not None else 8
    layout = ZoneFrame(mean_m=np.ones((grid, grid)), sigma_m=np.zeros((grid, grid)),
                       valid=np.ones((grid, grid), bool))
    if zone_rects is not None and rects_size is None:
        raise ValueError("zone_rects needs rects_size, the image size they refer to")
    feeds = []
    for index in picks.astype(int):
        frame = reader[index]
        size = frame.image.shape[:2]
        if zone_rects is None:
            rects = estimator.zone_rects_for(layout, size)
        else:
            rects = scale_rects(np.asarray(zone_rects, dtype=np.float32), rects_size, size)
        model = estimator.onnx_model
        slots = 1 if model is None else model.target_slots
        zones = simulate_zone_frame(frame.depth_m, rects, max_targets=slots)
        # The reading as a CX part reports it (no histogram), or for weights trained on
        # histograms as a CH part does, in ST's example CNH bins (`deltar simulate --cnh`).
        targets = {} if zones.target_mean_m is None else {
            name: getattr(zones, name) for name in ("target_mean_m", "target_sigma_m",
                                                    "target_valid", "target_signal")}
        if estimator.histogram_hypotheses:
            from deltar.sensor.cnh import CNHConfig, simulate_cnh

            cnh = CNHConfig()
            targets.update(hist_edges_m=cnh.edges_m().astype(np.float32),
                           hist_counts=simulate_cnh(frame.depth_m, rects, cnh)
                           .reshape(grid, grid, -1))
        reading = ZoneFrame(mean_m=zones.mean_m, sigma_m=zones.sigma_m, valid=zones.valid,
                            no_target=zones.no_target, **targets)
        inputs = estimator.prepare([frame.image], [reading], zone_rects=rects[None])
        names = list(INPUT_NAMES)
        if model is not None and model.takes_no_target:
            names.append(NO_TARGET_INPUT)
        if slots > 1:
            inputs[TARGETS_INPUT] = fixed_target_slots(inputs[TARGETS_INPUT],
                                                       inputs["zone_valid"].shape, slots)
            names.append(TARGETS_INPUT)
        feeds.append({name: inputs[name] for name in names})
    return feeds


@contextlib.contextmanager
def _quiet_quantizer() -> Iterator[None]:
    # onnxruntime's quantiser logs advice through the root logger at WARNING level.
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(previous)


class _FeedReader:
    """onnxruntime ``CalibrationDataReader`` over a list of feed dicts."""

    def __init__(self, feeds: Sequence[dict[str, np.ndarray]]) -> None:
        self._feeds: Iterator[dict[str, np.ndarray]] = iter(feeds)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def quantize_onnx(float_path: str | os.PathLike, out_path: str | os.PathLike,
                  feeds: Sequence[dict[str, np.ndarray]], *,
                  op_types: Sequence[str] = ("Conv",), overwrite: bool = False) -> Path:
    """Write a statically quantised (int8, QDQ) copy of an exported model, atomically.

    Args:
        float_path: float32 ``.onnx`` file from :func:`~deltar.export.onnx.export_onnx`.
        out_path: destination ``.onnx`` file (must differ from ``float_path``).
        feeds: calibration inputs (:func:`calibration_feeds`), at least one.
        op_types: operator types quantised (outside the float head); "Conv" by default,
            add "MatMul" to quantise the attention and resampling products too.
        overwrite: replace an existing ``out_path`` (default: ``FileExistsError``).

    Returns:
        The written path.
    """
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from deltar.inference.onnx_runtime import SIGNATURE_KEY
    from deltar.io.atomic import atomic_path

    float_path, out_path = Path(float_path), Path(out_path)
    input_file(float_path, "ONNX model")
    if out_path.resolve() == float_path.resolve():
        raise ValueError(f"out_path must differ from the float model {float_path}")
    if out_path.exists() and not overwrite:
        raise FileExistsError(f"refusing to overwrite existing file: {out_path}")
    if not feeds:
        raise ValueError("quantisation needs at least one calibration feed")
    proto = onnx.load(str(float_path))
    metadata = {entry.key: entry.value for entry in proto.metadata_props}
    if SIGNATURE_KEY not in metadata:
        raise ValueError(f"{float_path}: no {SIGNATURE_KEY} metadata (export with deltar "
                         "export)")
    if QUANT_KEY in metadata:
        raise ValueError(f"{float_path}: already quantised ({metadata[QUANT_KEY]})")
    with atomic_path(out_path, overwrite=overwrite) as tmp, _quiet_quantizer():
        # onnxruntime's pre-processing (graph optimisation, shape inference) first: it
        # folds the graph so that more convolutions quantise to fused int8 kernels.
        prepared = tmp.with_name(tmp.name + ".prepared.onnx")
        try:
            quant_pre_process(str(float_path), str(prepared), skip_symbolic_shape=True)
            graph = onnx.load(str(prepared)).graph
            excluded = [node.name for node in graph.node
                        if any(part in node.name for part in FLOAT_PARTS)]
            # uint8 activations with int8 weights: the fast x86 path of onnxruntime.
            quantize_static(str(prepared), str(tmp), _FeedReader(feeds),
                            quant_format=QuantFormat.QDQ, op_types_to_quantize=list(op_types),
                            per_channel=True, activation_type=QuantType.QUInt8,
                            weight_type=QuantType.QInt8, nodes_to_exclude=excluded,
                            calibrate_method=CalibrationMethod.MinMax)
        finally:
            prepared.unlink(missing_ok=True)
        quantized = onnx.load(str(tmp))
        del quantized.metadata_props[:]
        description = (f"static QDQ: uint8 activations, int8 per-channel weights, "
                       f"{'+'.join(op_types)} outside the head; MinMax ranges from "
                       f"{len(feeds)} calibration frames")
        for key, value in {**metadata, QUANT_KEY: description}.items():
            entry = quantized.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(quantized, str(tmp))
    return out_path


def export_int8(model, path: str | os.PathLike, height: int, width: int,
                calibration: str | os.PathLike | Sequence, *, frames: int = 16,
                zone_rects: np.ndarray | None = None, overwrite: bool = False,
                metadata: dict[str, str] | None = None) -> Path:
    """Export ``model`` to ONNX and write only its int8 quantisation to ``path``.

    The float32 export goes to a temporary folder; calibration runs it on ``frames``
    frames of the RGB-D folder ``calibration`` (:func:`calibration_feeds`).

    Args:
        model: the network (``DeltarNet``).
        path: destination ``.onnx`` file.
        height, width: camera image size in pixels (as :func:`~deltar.export.onnx.export_onnx`).
        calibration: RGB-D folder with calibration frames, or its reader
            (:func:`open_calibration_frames`).
        frames: number of calibration frames.
        zone_rects: (Z, 4) zone layout in image pixels; the nominal one when None.
        overwrite: replace an existing file (default: ``FileExistsError``).
        metadata: extra string key/values stored in the model.

    Returns:
        The written path.
    """
    import tempfile

    from deltar.export.onnx import export_onnx
    from deltar.inference.loading import load_estimator

    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"refusing to overwrite existing file: {path}")
    if isinstance(calibration, (str, os.PathLike)):  # checked before the long export
        calibration = open_calibration_frames(calibration)
    with tempfile.TemporaryDirectory(prefix="deltar-int8-") as folder:
        float_path = Path(folder) / "float32.onnx"
        export_onnx(model, float_path, height, width, zone_rects=zone_rects,
                    metadata=metadata)
        estimator = load_estimator(float_path, kind="onnx")
        feeds = calibration_feeds(estimator, calibration, frames, zone_rects=zone_rects,
                                  rects_size=(height, width))
        return quantize_onnx(float_path, path, feeds, overwrite=overwrite)
