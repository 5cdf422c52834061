"""Run an exported DeltarNet (``deltar export``) with onnxruntime: ``OnnxDepthModel``.

An ONNX file has a dynamic batch axis and a fixed input size. Parts of the zone fusion
take their shapes from the zone layout (tokens per zone patch, the longest zone
window), so the export fixes them too: a file serves every zone layout with the same
*layout signature* (:func:`layout_signature`: same patch sizes, windows no longer than
at export). The signature is stored in the file's metadata and checked before every
run, so a layout that does not fit raises a clear error instead of giving wrong depth.

This is the runtime side of :mod:`deltar.export.onnx` (which writes the files): the
input and output names, the metadata keys and the signature live here, so the
estimator runs ONNX files without importing the exporter.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.contract import network_contract
from deltar.io.input_file import input_file

if TYPE_CHECKING:
    import torch

INPUT_NAMES = ("image", "hypotheses", "zone_rects", "zone_valid")
#: The optional fifth input of networks whose head uses the no-target flags.
NO_TARGET_INPUT = "zone_no_target"
OUTPUT_NAMES = ("depth", "bin_edges", "uncertainty")
#: Metadata key of the layout signature an ONNX file was exported for.
SIGNATURE_KEY = "deltar_layout_signature"


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
        input_size: (H, W) fixed input size in pixels.
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
        if names not in (list(INPUT_NAMES), [*INPUT_NAMES, NO_TARGET_INPUT]):
            raise ValueError(f"{path}: inputs are {names}, expected {list(INPUT_NAMES)} "
                             f"(and optionally {NO_TARGET_INPUT!r}; export with deltar export)")
        #: Whether the graph takes the (B, Z) bool no-target flags.
        self.takes_no_target = NO_TARGET_INPUT in names
        meta = self.session.get_modelmeta().custom_metadata_map
        if SIGNATURE_KEY not in meta:
            raise ValueError(f"{path}: no {SIGNATURE_KEY} metadata (export with deltar export)")
        self.signature = json.loads(meta[SIGNATURE_KEY])
        self.grid = int(meta["deltar_grid"])
        self.metadata = dict(meta)
        shapes = {i.name: i.shape for i in self.session.get_inputs()}
        self.input_size = (int(shapes["image"][2]), int(shapes["image"][3]))
        self.num_hypotheses = int(shapes["hypotheses"][2])
        try:
            config = json.loads(meta.get("deltar_config", "{}"))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: unreadable deltar_config metadata: {err}") from err
        self.contract = {**network_contract(config), "num_hypotheses": self.num_hypotheses}

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

    def run(self, image: np.ndarray, hypotheses: np.ndarray, zone_rects: np.ndarray,
            zone_valid: np.ndarray, zone_no_target: np.ndarray | None = None
            ) -> dict[str, np.ndarray]:
        """Run the network; same inputs and outputs as ``DeltarNet.forward`` (numpy).

        Args:
            image: (B, 3, H, W) float32 normalised, H x W = :attr:`input_size`.
            hypotheses: (B, Z, K) float32 metres.
            zone_rects: (B, Z, 4) float32 pixels of the input.
            zone_valid: (B, Z) bool.
            zone_no_target: optional (B, Z) bool no-target flags (all False when None);
                used by graphs that take them (:attr:`takes_no_target`), else ignored.

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
        if self.takes_no_target:
            flags = (np.zeros(feeds["zone_valid"].shape, dtype=bool) if zone_no_target is None
                     else np.asarray(zone_no_target, dtype=bool))
            if flags.shape != feeds["zone_valid"].shape:
                raise ValueError(f"zone_no_target must have the shape of zone_valid "
                                 f"{feeds['zone_valid'].shape}, got {flags.shape}")
            feeds[NO_TARGET_INPUT] = flags
        outputs = self.session.run(list(OUTPUT_NAMES), feeds)
        return dict(zip(OUTPUT_NAMES, outputs, strict=True))
