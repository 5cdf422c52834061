"""Run an exported DeltarNet (``deltar export``) with onnxruntime: ``OnnxDepthModel``.

An ONNX file has a dynamic batch axis and a fixed input size. Parts of the zone fusion
take their shapes from the zone layout (tokens per zone patch, the longest zone
window), so the export fixes them too: a file serves every zone layout with the same
*layout signature* (:func:`layout_signature`: same patch sizes, windows no longer than
at export). The signature is stored in the file's metadata and checked before every
run, so a layout that does not fit raises a clear error instead of giving wrong depth.

One network exported at several input sizes (:func:`deltar.export.onnx.export_onnx_sizes`:
one file per size, the weights shared) lists its files in each file's metadata
(:data:`SIZES_KEY`); ``OnnxDepthModel`` of any of them loads another size's file when an
image of that size comes (:meth:`OnnxDepthModel.for_input_size`).

This is the runtime side of :mod:`deltar.export.onnx` (which writes the files): the
input and output names, the metadata keys and the signature live here, so the
estimator runs ONNX files without importing the exporter.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.contract import network_contract
from deltar.extras import pytorch_remedy, torch_available
from deltar.io.input_file import input_file
from deltar.sensor.targets import fixed_target_slots

if TYPE_CHECKING:
    import torch

INPUT_NAMES = ("image", "hypotheses", "zone_rects", "zone_valid")
#: The optional fifth input of networks whose head uses the no-target flags.
NO_TARGET_INPUT = "zone_no_target"
OUTPUT_NAMES = ("depth", "bin_edges", "uncertainty")
#: The optional input of graphs that read several targets per zone: (B, Z, T, 2)
#: ``[distance, share]`` (:func:`deltar.sensor.targets.target_inputs`).
TARGETS_INPUT = "zone_targets"
#: Metadata key of the layout signature an ONNX file was exported for.
SIGNATURE_KEY = "deltar_layout_signature"
#: Metadata key of the files of one network exported at several input sizes: JSON
#: {"<h>x<w>": file name beside this one}.
SIZES_KEY = "deltar_input_sizes"


def size_text(size: tuple[int, int]) -> str:
    """``"<h>x<w>"`` of an (H, W) size in pixels."""
    return f"{int(size[0])}x{int(size[1])}"


def sized_file_name(name: str, size: tuple[int, int]) -> str:
    """The file name of another input size's export beside ``name``: ``<stem>.<h>x<w>.onnx``."""
    stem = name[:-len(".onnx")] if name.endswith(".onnx") else name
    return f"{stem}.{size_text(size)}.onnx"


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


def signature_fits(signature: list[dict], exported: list[dict]) -> bool:
    """True when a layout's signature fits one an ONNX file was exported for."""
    return all(s["patch"] == e["patch"] and s["max_length"][0] <= e["max_length"][0]
               and s["max_length"][1] <= e["max_length"][1]
               for s, e in zip(signature, exported, strict=True))


class OnnxDepthModel:
    """An exported DeltarNet run with onnxruntime on the CPU.

    Args:
        path: the ``.onnx`` file written by :func:`deltar.export.onnx.export_onnx`.
        num_threads: onnxruntime intra-op threads (its default when None).
        allow_spinning: let onnxruntime's idle worker threads busy-wait for the next
            run (its default). Off by default here: between runs the pipeline's own
            work (decoding, resizing) needs those cores.

    Attributes:
        input_size: (H, W) fixed input size in pixels of this file.
        input_sizes: every (H, W) input size the network was exported at, this file's
            first (:data:`SIZES_KEY`; just ``input_size`` for a file exported alone).
        num_hypotheses: K hypotheses per zone.
        grid: zones per side.
        contract: the contract the exported network's config (``deltar_config``
            metadata, either stored form) carries, flat
            (:func:`deltar.contract.network_contract`): ``image_mean``, ``image_std``,
            ``hypothesis_sampling``, ``num_hypotheses``, ...; files without it get the
            release's ImageNet normalisation and inverse-CDF sampling.
    """

    def __init__(self, path: str | os.PathLike, num_threads: int | None = None,
                 allow_spinning: bool = False) -> None:
        import onnxruntime as ort

        path = Path(path)
        input_file(path, "ONNX model")
        self._options = (num_threads, allow_spinning)
        options = ort.SessionOptions()
        if num_threads:
            from deltar.io.resources import check_threads

            options.intra_op_num_threads = check_threads(num_threads, "num_threads")
            options.inter_op_num_threads = 1
        if not allow_spinning:
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        # Fatal only (its errors are level 3): onnxruntime's own coloured log line would
        # precede and repeat the ValueError below, which names the file.
        options.log_severity_level = 4
        try:
            self.session = ort.InferenceSession(str(path), options,
                                                providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types
            raise ValueError(f"{path}: cannot load ONNX model: {err}") from err
        self.path = path
        names = [i.name for i in self.session.get_inputs()]
        if names not in (list(INPUT_NAMES), [*INPUT_NAMES, NO_TARGET_INPUT],
                         [*INPUT_NAMES, NO_TARGET_INPUT, TARGETS_INPUT]):
            raise ValueError(f"{path}: inputs are {names}, expected {list(INPUT_NAMES)} "
                             f"(and optionally {NO_TARGET_INPUT!r}, {TARGETS_INPUT!r}; export "
                             "with deltar export)")
        #: Whether the graph takes the (B, Z) bool no-target flags.
        self.takes_no_target = NO_TARGET_INPUT in names
        if SIGNATURE_KEY not in self.session.get_modelmeta().custom_metadata_map:
            raise ValueError(f"{path}: no {SIGNATURE_KEY} metadata (export with deltar export)")
        try:  # a file edited or written by another tool: one error naming it
            self._read_metadata(path)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
            what = f"no {err.args[0]} metadata" if isinstance(err, KeyError) else err
            raise ValueError(f"{path}: cannot read its deltar metadata: {what} (export "
                             "with deltar export)") from err
        for size, other in self._files.items():
            if not other.is_file():
                raise ValueError(f"{path}: the {size_text(size)} export it lists, {other}, "
                                 "is missing (keep the files of one export together)")
        self.input_sizes = tuple(self._files)
        self._loaded: dict[tuple[int, int], OnnxDepthModel] = {self.input_size: self}

    def _read_metadata(self, path: Path) -> None:
        """Set the grid, signature, sizes and contract from the file's inputs and metadata.

        Raises:
            KeyError (the missing key), TypeError or ValueError: metadata not as
            ``deltar export`` writes it.
        """
        inputs = {i.name: i.shape for i in self.session.get_inputs()}
        #: Target slots per zone the graph reads (1: the primary reading alone).
        self.target_slots = (_dimension(inputs[TARGETS_INPUT], 2, TARGETS_INPUT)
                             if TARGETS_INPUT in inputs else 1)
        meta = self.session.get_modelmeta().custom_metadata_map
        self.metadata = dict(meta)
        self.signature = _json_value(meta, SIGNATURE_KEY, list)
        if not all(isinstance(s, dict) and {"patch", "max_length"} <= set(s)
                   for s in self.signature):
            raise ValueError(f"{SIGNATURE_KEY} must list {{stride, patch, max_length}} "
                             f"per fusion stride, got {meta[SIGNATURE_KEY][:80]!r}")
        self.grid = _positive_int(meta["deltar_grid"], "deltar_grid")
        self.input_size = (_dimension(inputs["image"], 2, "image"),
                           _dimension(inputs["image"], 3, "image"))
        self.num_hypotheses = _dimension(inputs["hypotheses"], 2, "hypotheses")
        config = _json_value(meta, "deltar_config", dict, default="{}")
        self.contract = {**network_contract(config), "num_hypotheses": self.num_hypotheses}
        self._files = {self.input_size: path}
        for text, name in _json_value(meta, SIZES_KEY, dict, default="{}").items():
            height, width = (_positive_int(v, SIZES_KEY) for v in str(text).split("x"))
            if (height, width) != self.input_size:
                self._files[(height, width)] = path.with_name(Path(str(name)).name)

    def for_input_size(self, size: tuple[int, int]) -> OnnxDepthModel:
        """The model for (H, W) input images of ``size`` pixels (one of :attr:`input_sizes`):
        this one or another size's file, loaded on first use with the same options.

        Raises:
            ValueError: a size the network was not exported at, or a file that is not
                an export of the same network (another contract, grid or inputs).
        """
        size = (int(size[0]), int(size[1]))
        if size not in self._loaded:
            if size not in self._files:
                raise ValueError(f"{self.path}: no export for {size_text(size)} inputs (it "
                                 f"has {', '.join(size_text(s) for s in self.input_sizes)})")
            other = OnnxDepthModel(self._files[size], *self._options)
            if (other.input_size != size or other.contract != self.contract
                    or other.grid != self.grid or other.takes_no_target != self.takes_no_target
                    or other.target_slots != self.target_slots):
                raise ValueError(f"{other.path} is not the {size_text(size)} export of the "
                                 f"network in {self.path}")
            self._loaded[size] = other
        return self._loaded[size]

    def check_grid(self, grid: int, name: str = "zone frames") -> None:
        """Raise ``ValueError`` naming ``name`` when zone frames of ``grid`` x ``grid``
        zones are not the exported network's grid (its inputs have a fixed zone count)."""
        if int(grid) != self.grid:
            raise ValueError(f"{name} has {grid}x{grid} zones, but the ONNX model {self.path} "
                             f"takes {self.grid}x{self.grid} zone frames; "
                             f"{pytorch_remedy('runs any grid')}, or export "
                             f"it for {grid}x{grid} zones (deltar export --layout-from a "
                             "calibration or recording of that grid)")

    def check_layout(self, zone_rects: np.ndarray) -> None:
        """Raise ``ValueError`` if a (B, Z, 4) layout does not fit the exported one.

        A file exported from a network without zone-patch fusion (empty signature) takes
        any layout of its grid.
        """
        rects = np.asarray(zone_rects, dtype=np.float32)
        if rects.ndim != 3 or rects.shape[1] != self.grid * self.grid or rects.shape[2] != 4:
            raise ValueError(f"zone_rects must be (B, {self.grid * self.grid}, 4), got "
                             f"{rects.shape}")
        if not self.signature:  # the graph does not depend on the layout's shape
            return
        signature = layout_signature(rects, self.grid)
        if not signature_fits(signature, self.signature):
            raise ValueError(f"{self.path}: this zone layout {signature} does not fit the one "
                             f"the model was exported for {self.signature}; re-export with "
                             "this layout (deltar export --layout-from) or use the PyTorch "
                             "backend")

    def warn_if_stretched(self, image_size: tuple[int, int], net_size: tuple[int, int]
                          ) -> None:
        """Warn when the exported sizes stretch an image of ``image_size`` (H, W pixels)
        to ``net_size`` where the weights' size rule would run it at another size, as
        PyTorch does. Each call warns: the caller's warning filters decide what is shown
        (Python's default shows each size's warning once)."""
        from deltar.inference.preprocess import network_input_size

        design = self.contract.get("design_size")
        if design is None:
            return
        rule = network_input_size(*image_size, design_size=tuple(design))
        if tuple(rule) != tuple(net_size):
            remedy = ("use the PyTorch backend (without --onnx) for that" if torch_available()
                      else 'pip install "deltar[torch]" for that')
            warnings.warn(f"{image_size[0]}x{image_size[1]} images are stretched to the ONNX "
                          f"model's {net_size[0]}x{net_size[1]} input, the exported size "
                          f"nearest in aspect (PyTorch runs them at {rule[0]}x{rule[1]}; "
                          f"{remedy}, or export for this size with deltar export --size)",
                          UserWarning, stacklevel=3)

    def run(self, image: np.ndarray, hypotheses: np.ndarray, zone_rects: np.ndarray,
            zone_valid: np.ndarray, zone_no_target: np.ndarray | None = None,
            zone_targets: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Run the network; same inputs and outputs as ``DeltarNet.forward`` (numpy).

        Args:
            image: (B, 3, H, W) float32 normalised, H x W one of :attr:`input_sizes`
                (run by that size's file).
            hypotheses: (B, Z, K) float32 metres.
            zone_rects: (B, Z, 4) float32 pixels of the input.
            zone_valid: (B, Z) bool.
            zone_no_target: optional (B, Z) bool no-target flags (all False when None);
                used by graphs that take them (:attr:`takes_no_target`), else ignored.
            zone_targets: optional (B, Z, T, 2) float32 every target of each zone
                (:func:`deltar.sensor.targets.target_inputs`); graphs that read targets
                (:attr:`target_slots` > 1) get them padded or cut to their T (none: the
                primary readings alone), other graphs ignore them.

        Returns:
            dict of ``depth`` (B, 1, H/2, W/2), ``bin_edges`` (B, N + 1) and
            ``uncertainty`` (B, 1, H/2, W/2), float32 metres.
        """
        image = np.asarray(image, dtype=np.float32)
        if image.ndim != 4 or image.shape[1] != 3 or tuple(image.shape[2:]) not in self._files:
            sizes = " or ".join(size_text(s) for s in self.input_sizes)
            raise ValueError(f"image must be (B, 3, H, W) with H x W {sizes}, got "
                             f"{image.shape}")
        if tuple(image.shape[2:]) != self.input_size:
            return self.for_input_size(image.shape[2:]).run(image, hypotheses, zone_rects,
                                                              zone_valid, zone_no_target,
                                                              zone_targets)
        hyp = np.asarray(hypotheses, dtype=np.float32)
        if hyp.ndim != 3 or hyp.shape[2] != self.num_hypotheses or not np.all(np.isfinite(hyp)):
            raise ValueError(f"hypotheses must be finite (B, Z, {self.num_hypotheses}), got "
                             f"{hyp.shape}")
        self.check_layout(zone_rects)
        feeds = {"image": image, "hypotheses": hyp,
                 "zone_rects": np.asarray(zone_rects, dtype=np.float32),
                 "zone_valid": np.asarray(zone_valid, dtype=bool)}
        if self.takes_no_target:
            flags = (np.zeros(feeds["zone_valid"].shape, dtype=bool) if zone_no_target is None
                     else np.asarray(zone_no_target, dtype=bool))
            if flags.shape != feeds["zone_valid"].shape:
                raise ValueError(f"zone_no_target must have the shape of zone_valid "
                                 f"{feeds['zone_valid'].shape}, got {flags.shape}")
            feeds[NO_TARGET_INPUT] = flags
        if self.target_slots > 1:
            feeds[TARGETS_INPUT] = fixed_target_slots(zone_targets, feeds["zone_valid"].shape,
                                                      self.target_slots)
        outputs = self.session.run(list(OUTPUT_NAMES), feeds)
        return dict(zip(OUTPUT_NAMES, outputs, strict=True))


def _json_value(meta: dict, key: str, kind: type, default: str | None = None):
    """The JSON value of metadata ``key``, which must be a ``kind`` (KeyError if absent
    without a default)."""
    text = meta[key] if default is None else meta.get(key, default)
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{key} is not JSON ({err})") from None
    if not isinstance(value, kind):
        raise ValueError(f"{key} must be a JSON {'list' if kind is list else 'object'}, "
                         f"got {text[:80]!r}")
    return value


def _positive_int(text, name: str) -> int:
    """``text`` as a positive whole number; ``ValueError`` naming ``name`` otherwise."""
    try:
        value = int(text)
    except (TypeError, ValueError):
        value = 0
    if value < 1:
        raise ValueError(f"{name} must be a positive whole number, got {text!r}")
    return value


def _dimension(shape: list, axis: int, name: str) -> int:
    """A fixed axis of an input's shape (onnxruntime gives a symbolic one as text)."""
    value = shape[axis] if len(shape) > axis else None
    if not isinstance(value, int) or value < 1:
        raise ValueError(f"input {name!r} has shape {shape}; axis {axis} must be fixed "
                         "(deltar export fixes every axis but the batch)")
    return value
