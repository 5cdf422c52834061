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
import copy
import functools
import json
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.export.graph_rewrites import (
    fold_pads_into_convs,
    merge_equal_constants,
    name_constants_by_contents,
    point_to_shared,
    shared_weights,
    short_value_names,
    single_target_branch,
)
from deltar.inference.onnx_runtime import (
    INPUT_NAMES,
    NO_TARGET_INPUT,
    OUTPUT_NAMES,
    SIGNATURE_KEY,
    SIZES_KEY,
    TARGETS_INPUT,
    layout_signature,
    size_text,
    sized_file_name,
)

if TYPE_CHECKING:
    import onnx
    import torch

    from deltar.models import DeltarNet

OPSET = 17
__all__ = ["OPSET", "example_inputs", "export_input_size", "export_onnx", "export_onnx_sizes"]


def _tuple_outputs(model: DeltarNet) -> torch.nn.Module:
    """Wrap DeltarNet so the traced graph returns (depth, bin_edges, uncertainty)."""
    import torch

    class TupleOutputs(torch.nn.Module):
        def __init__(self, inner: DeltarNet) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, image, hypotheses, zone_rects, zone_valid, zone_no_target=None,
                    zone_targets=None):
            out = self.inner(image, hypotheses, zone_rects, zone_valid,
                             zone_no_target=zone_no_target, zone_targets=zone_targets)
            return out["depth"], out["bin_edges"], out["uncertainty"]

    return TupleOutputs(model).eval()


def export_input_size(model: DeltarNet, height: int, width: int) -> tuple[int, int]:
    """The fixed (H, W) network input, pixels, of an export for ``height`` x ``width`` images.

    The one size rule (:func:`~deltar.inference.preprocess.network_input_size`) with the
    model's design size: the size ``DepthEstimator`` runs the model at for such images.
    """
    from deltar.inference.preprocess import network_input_size

    return network_input_size(height, width, design_size=model.network_config.inputs.design_size)


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
        zone_no_target (1, Z) all False for a network whose head uses the flags, and
        zone_targets (1, Z, NETWORK_TARGET_SLOTS, 2) for one whose head reads several
        targets per zone (the primary reading in slot 0, a second target in slot 1).
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
    k = model.network_config.inputs.num_hypotheses
    hypotheses = torch.linspace(1.8, 2.2, k).expand(1, zones, k).contiguous()
    inputs = (torch.zeros(1, 3, net_height, net_width), hypotheses,
              torch.from_numpy(rects)[None], torch.ones(1, zones, dtype=torch.bool))
    if getattr(model, "uses_no_target", False):
        # The head reads the flags: the export takes them as a fifth input.
        inputs += (torch.zeros(1, zones, dtype=torch.bool),)
        if getattr(model, "uses_targets", False):
            from deltar.sensor.targets import NETWORK_TARGET_SLOTS

            # And the targets as a sixth: traced with a second target in every zone, so
            # the graph keeps the branch that reads them.
            targets = torch.zeros(1, zones, NETWORK_TARGET_SLOTS, 2)
            targets[..., 0, 0], targets[..., 0, 1] = 2.0, 0.7
            targets[..., 1:, 0], targets[..., 1:, 1] = 3.0, 0.3 / (NETWORK_TARGET_SLOTS - 1)
            inputs += (targets,)
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

    if not isinstance(model, torch.nn.Module) or not hasattr(model, "config"):
        raise ValueError(f"model must be a DeltarNet (e.g. load_checkpoint(path)[0]), got "
                         f"{type(model).__name__}")
    if not all(isinstance(v, int | np.integer) and not isinstance(v, bool) and v >= 1
               for v in (height, width)):
        raise ValueError(f"height and width must be positive whole pixels, got "
                         f"{height!r}x{width!r}")
    if zone_rects is not None:
        zone_rects = np.asarray(zone_rects, dtype=np.float32)
        if zone_rects.ndim != 2 or zone_rects.shape[1] != 4 or \
                round(zone_rects.shape[0] ** 0.5) ** 2 != zone_rects.shape[0] or \
                not np.all(np.isfinite(zone_rects)):
            raise ValueError(f"zone_rects must be (Z, 4) finite (y0, x0, y1, x1) pixels of "
                             f"an n x n grid, got shape {zone_rects.shape}")
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"refusing to overwrite existing file: {path}")
    # A copy: the caller's model keeps its mode, dtype and device.
    model = copy.deepcopy(model).eval().float().cpu()
    inputs = example_inputs(model, height, width, zone_rects)
    grid = round(inputs[2].shape[1] ** 0.5)
    # Only the zone-patch fusion bakes the layout's shape into the graph; a network
    # without it (e.g. the plane-select one) takes any layout, which an empty signature
    # records.
    uses_patches = getattr(model, "distribution_encoder", None) is not None
    signature = layout_signature(inputs[2].numpy(), grid) if uses_patches else []
    input_names = [*INPUT_NAMES, NO_TARGET_INPUT, TARGETS_INPUT][:len(inputs)]
    dynamic = {name: {0: "batch"} for name in (*input_names, *OUTPUT_NAMES)}
    net_height, net_width = inputs[0].shape[-2:]
    traced = _tuple_outputs(model)
    with atomic_path(path, overwrite=overwrite) as tmp, _traceable(model), \
            torch.no_grad(), _quiet_tracer(), _static_same_padding(traced, inputs):

        def trace(count: int) -> onnx.ModelProto:
            names = input_names[:count]
            torch.onnx.export(traced, inputs[:count], str(tmp), input_names=names,
                              output_names=list(OUTPUT_NAMES),
                              dynamic_axes={k: v for k, v in dynamic.items()
                                            if k in names or k in OUTPUT_NAMES},
                              opset_version=OPSET, dynamo=False)
            traced_proto = onnx.load(str(tmp))
            fold_pads_into_convs(traced_proto)
            return traced_proto

        proto = trace(len(inputs))
        if TARGETS_INPUT in input_names:
            # Frames whose zones report one target each (most) run the graph traced
            # without the targets, the same outputs in less time.
            proto = single_target_branch(proto, trace(len(inputs) - 1))
        merge_equal_constants(proto)
        short_value_names(proto)
        extra = {SIGNATURE_KEY: json.dumps(signature), "deltar_grid": str(grid),
                 "deltar_image_size": f"{height}x{width}",
                 "deltar_input_size": f"{net_height}x{net_width}",
                 "deltar_config": json.dumps(model.config(), default=list),
                 **(metadata or {})}
        for key, value in extra.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, str(value)
        onnx.save(proto, str(tmp))
    return path


def sized_export_paths(model: DeltarNet, path: str | os.PathLike,
                       image_sizes: list[tuple[int, int]]) -> dict[tuple[int, int], Path]:
    """The files :func:`export_onnx_sizes` writes, by network input size (H, W): ``path``
    for the first size, ``<stem>.<h>x<w>.onnx`` beside it for the others (camera sizes
    that give a network size already listed add none). The weights go to
    ``<path>.data`` besides.

    Raises:
        ValueError: no image size, or a non-positive one.
    """
    return _paths_by_size(Path(path), _camera_size_by_network_size(model, image_sizes))


def _camera_size_by_network_size(model: DeltarNet, image_sizes: list[tuple[int, int]]
                                 ) -> dict[tuple[int, int], tuple[int, int]]:
    """The first camera size (H, W) of each distinct network input size, in order.

    Raises:
        ValueError: no image size, or a non-positive one.
    """
    if not image_sizes:
        raise ValueError("image_sizes must name at least one (height, width) camera size")
    by_network: dict[tuple[int, int], tuple[int, int]] = {}
    for height, width in image_sizes:
        if height < 1 or width < 1:
            raise ValueError(f"image sizes must be positive, got {height}x{width}")
        by_network.setdefault(export_input_size(model, height, width), (height, width))
    return by_network


def _paths_by_size(path: Path, sizes: Iterable[tuple[int, int]]) -> dict[tuple[int, int], Path]:
    """``path`` for the first network size, ``<stem>.<h>x<w>.onnx`` beside it for the rest."""
    return {size: path if i == 0 else path.with_name(sized_file_name(path.name, size))
            for i, size in enumerate(sizes)}


def export_onnx_sizes(model: DeltarNet, path: str | os.PathLike,
                      image_sizes: list[tuple[int, int]], *, overwrite: bool = False,
                      metadata: dict[str, str] | None = None) -> list[Path]:
    """Export ``model`` for several camera image sizes, the files sharing one weights file.

    Each distinct network input size (:func:`export_input_size` of a camera size: the one
    size rule) gets its own fixed-size file, :func:`export_onnx`'s graph: the first at
    ``path``, the others beside it as ``<stem>.<h>x<w>.onnx`` (network input size in
    pixels; :func:`sized_export_paths`). Their weights are the same, so they are written
    once, to ``<path>.data`` (ONNX external data, which onnxruntime reads from beside the
    file): an extra size costs its graph alone. Every file lists all the sizes in its
    ``deltar_input_sizes`` metadata, so :class:`~deltar.inference.onnx_runtime.OnnxDepthModel`
    of the first runs each image at the size the size rule gives it (PyTorch's size),
    when listed.

    The files are written beside their final names and moved there only once all are
    written: a failure leaves none of them under the final names, and files they replace
    with ``overwrite`` as they were (also when the failure comes while moving).

    Args:
        model: the network, as for :func:`export_onnx`.
        path: the first size's ``.onnx`` file.
        image_sizes: (H, W) camera image sizes in pixels; sizes that give a network
            input size already listed are skipped.
        overwrite: replace existing files (default: ``FileExistsError``).
        metadata: extra string key/values stored in every file.

    Returns:
        The written ``.onnx`` paths, the first size's first, then the weights file.

    Raises:
        ValueError: no image size, a non-positive one, or a file to write that is a
            folder (named by its final path).
        FileExistsError: a file to write exists and ``overwrite`` is False.
    """
    import tempfile

    import onnx

    path = Path(path)
    by_network = _camera_size_by_network_size(model, image_sizes)
    files = _paths_by_size(path, by_network)
    data_path = path.with_name(path.name + ".data")
    targets = [*files.values(), data_path]
    for target in targets:  # checked before the long part, named as the user knows them
        if target.is_dir():
            raise ValueError(f"{target} is a folder, not a file (an export writes "
                             f"{', '.join(t.name for t in targets)} there)")
        if target.exists() and not overwrite:
            raise FileExistsError(f"refusing to overwrite existing file: {target} (overwrite "
                                  "replaces it: --overwrite)")
    listing = json.dumps({size_text(size): file.name for size, file in files.items()})
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".deltar-export-") as tmp:
        protos = {}
        for size in files:
            single = export_onnx(model, Path(tmp) / f"{size_text(size)}.onnx",
                                 *by_network[size], metadata=metadata)
            protos[size] = onnx.load(str(single))
        for proto in protos.values():
            name_constants_by_contents(proto)
        blob, where = shared_weights(list(protos.values()))
        staged = {data_path: Path(tmp) / "weights.data"}
        staged[data_path].write_bytes(blob)
        for size, proto in protos.items():
            point_to_shared(proto, where, data_path.name)
            entry = proto.metadata_props.add()
            entry.key, entry.value = SIZES_KEY, listing
            staged[files[size]] = Path(tmp) / f"{size_text(size)}.final.onnx"
            staged[files[size]].write_bytes(proto.SerializeToString())
        _move_all_into_place(staged, overwrite)
    return targets


def _move_all_into_place(staged: dict[Path, Path], overwrite: bool) -> None:
    """Move each staged file (same file system) onto its final path; if one move fails,
    put every final path back as it was: those moved are removed, or restored where they
    replaced a file (so no final name holds part of the set, and nothing is lost).

    Each file to be replaced is first hard-linked beside its staged one (a copy where the
    file system has no hard links): its final name keeps it throughout, and the staged
    copy's folder (a temporary) removes the backups with it.
    """
    import shutil

    from deltar.io.atomic import move_into_place

    backups: dict[Path, Path] = {}
    for final, tmp in staged.items():
        if overwrite and final.exists():
            backup = tmp.with_name(tmp.name + ".replaced")
            try:
                os.link(final, backup)
            except OSError:
                shutil.copy2(final, backup)
            backups[final] = backup
    moved: list[Path] = []
    try:
        for final, tmp in staged.items():
            move_into_place(tmp, final, overwrite)
            moved.append(final)
    except OSError as err:
        for done in moved:
            if done in backups:
                os.replace(backups[done], done)
            else:
                done.unlink(missing_ok=True)
        if isinstance(err, FileExistsError) or err.filename == str(final):
            raise
        # Name the output, not the hidden temporary it was written to.
        raise OSError(err.errno, err.strerror, str(final)) from err


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
def _static_same_padding(model: torch.nn.Module, inputs: tuple) -> Iterator[None]:
    """TensorFlow-style "same" convolutions padded by constants for the export.

    timm's ``Conv2dSame`` (the stride-2 convolutions of the ``tf_`` EfficientNets)
    computes its asymmetric zero padding from the input's shape at run time; traced,
    that becomes a chain of shape operators feeding a ``Pad``, which onnxruntime can
    neither fold nor fuse into the convolution (10% of the bundled network's time there).
    The inference rewrite :class:`~deltar.models.optimize.SymmetricSameConv2d` (a model
    prepared for inference) would trace a kernel of unknown shape. The export's input
    size is fixed, so each such convolution's input size is recorded in one forward pass
    and it runs as a constant ``Pad`` and a plain convolution of its own weights, which
    :func:`~deltar.export.graph_rewrites.fold_pads_into_convs` then merges. Same
    arithmetic; the modules are restored afterwards.
    """
    import torch.nn.functional as F
    from timm.layers import Conv2dSame, get_same_padding

    from deltar.models.optimize import SymmetricSameConv2d

    convs = [m for m in model.modules() if isinstance(m, (Conv2dSame, SymmetricSameConv2d))]
    sizes: dict[torch.nn.Module, tuple[int, int]] = {}
    hooks = [conv.register_forward_pre_hook(
        lambda module, args: sizes.__setitem__(module, tuple(args[0].shape[-2:])))
        for conv in convs]
    try:
        if convs:
            model(*inputs)
    finally:
        for hook in hooks:
            hook.remove()

    def padded(conv: torch.nn.Module, pads: tuple[int, int, int, int], x: torch.Tensor
               ) -> torch.Tensor:
        return F.conv2d(F.pad(x, pads), conv.weight, conv.bias, conv.stride, 0,
                        conv.dilation, conv.groups)

    for conv in convs:
        if conv in sizes:
            pad_h, pad_w = (get_same_padding(size, kernel, stride, dilation) for size, kernel,
                            stride, dilation in zip(sizes[conv], conv.kernel_size,
                                                    conv.stride, conv.dilation, strict=True))
            conv.forward = functools.partial(
                padded, conv, (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2))
    try:
        yield
    finally:
        for conv in convs:
            conv.__dict__.pop("forward", None)


@contextlib.contextmanager
def _quiet_tracer() -> Iterator[None]:
    # The tracer warns about every Python-side shape computation, which is expected
    # here (the layout signature is fixed on purpose and checked at run time).
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield
