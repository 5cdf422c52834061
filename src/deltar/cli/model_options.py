"""The model options of ``predict``, ``replay`` and ``wall-test``, defined once.

A command takes one parameter ``model: ModelOptions = MODEL_OPTIONS`` and is decorated with
:func:`model_options`; the decorator puts the twelve options in its place (same names
and help in every command) and hands the command a :class:`ModelOptions`, whose
:meth:`~ModelOptions.load` is :func:`deltar.inference.load_estimator`. ``export`` uses
the three weight options alone (:data:`PresetOption`, ...).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from deltar.cli.option_groups import option_group

if TYPE_CHECKING:
    from deltar.inference.estimator import DepthEstimator

PresetOption = Annotated[str | None, typer.Option(
    "--preset", help="Model preset (RANDOM weights: for testing the pipeline only).")]
CheckpointOption = Annotated[Path | None, typer.Option(
    "--checkpoint", help="deltar checkpoint (.pt) or a bundled model name; the bundled "
    "'default' model when no model option is given.")]
OfficialOption = Annotated[Path | None, typer.Option(
    "--official", help="Officially released weights (e.g. nyu.pt).")]
OnnxOption = Annotated[Path | None, typer.Option(
    "--onnx", help="ONNX model from 'deltar export' (onnxruntime backend), or 'default' "
    "for the bundled model's shipped export (also with PyTorch installed; a file named "
    "'default' here wins).")]
DeviceOption = Annotated[str, typer.Option(help="Torch device (PyTorch backend).")]
PrecisionOption = Annotated[str, typer.Option(
    help="float32, float16 or bfloat16 (PyTorch).")]
SizeOption = Annotated[str | None, typer.Option(
    "--size", help="Network input size HxW (multiples of 32); default: the size rule "
    "(the image's aspect kept at the weights' design pixel count, sides rounded to "
    "multiples of 32; docs/inference.md).")]
ThreadsOption = Annotated[int | None, typer.Option(
    "--threads", min=1, help="CPU threads (torch / onnxruntime).")]
FlipOption = Annotated[bool, typer.Option(
    "--flip", help="Test-time flip averaging: also run the mirrored image and zones and "
    "average (2x network time; PyTorch backends).")]
NetworkOnlyOption = Annotated[bool, typer.Option(
    "--network-only", help="The network's depth alone, without the confidence blend with "
    "the colorization fill of the zones that plane-select models (the bundled default) use "
    "by default: a little faster; on new rooms higher RMSE beyond the sensor's range, "
    "slightly lower errors within it (docs/inference.md).")]

KeepUnflaggedOption = Annotated[bool, typer.Option(
    "--no-inferred-flags", help="For zone frames without no-target flags (e.g. ZJU-L5 "
    "files), read no invalid zone as beyond the range; by default the estimator infers the "
    "flags by the rule the weights carry (docs/inference.md).")]
KeepOutliersOption = Annotated[bool, typer.Option(
    "--keep-outlier-zones", help="Use every valid zone; by default the estimator sets aside "
    "zones that disagree with all their neighbours by the rule the weights carry, if any "
    "(docs/inference.md).")]


def parse_size(text: str | None, option: str = "--size") -> tuple[int, int] | None:
    """``"480x640"`` -> (480, 640) pixels; None stays None.

    Raises:
        typer.BadParameter: not ``<int>x<int>``, naming ``option``.
    """
    if text is None:
        return None
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise typer.BadParameter(f"size must look like 480x640, got {text!r}",
                                 param_hint=option) from err
    return height, width


@dataclass(frozen=True)
class ModelOptions:
    """The model chosen on the command line (the CLI's view of ``load_estimator``)."""

    preset: str | None = None
    checkpoint: Path | None = None
    official: Path | None = None
    onnx: Path | None = None
    device: str = "cpu"
    precision: str = "float32"
    size: str | None = None
    threads: int | None = None
    flip: bool = False
    network_only: bool = False
    no_inferred_flags: bool = False
    keep_outlier_zones: bool = False

    def source(self) -> tuple[str | Path | None, str | None]:
        """``(source, kind)`` for :func:`~deltar.inference.load_estimator`."""
        for kind in ("preset", "checkpoint", "official", "onnx"):
            value = getattr(self, kind)
            if value is not None:
                return value, kind
        return None, None

    def given_options(self) -> list[str]:
        """The options given other than at their defaults (``["--flip", "--size"]``)."""
        return [f"--{f.name.replace('_', '-')}" for f in fields(self)
                if getattr(self, f.name) != f.default]

    def input_files(self) -> list[Path]:
        """The model files given (``--checkpoint``, ``--official``, ``--onnx`` and an ONNX
        file's external weights): inputs no output may replace."""
        files = [path for path in (self.checkpoint, self.official, self.onnx) if path]
        if self.onnx is not None:
            files.append(Path(f"{self.onnx}.data"))
        return files

    def check(self) -> None:
        """Usage checks that need no model (run before any work).

        Raises:
            typer.BadParameter: two model options, ``--flip`` with ``--onnx``, an unknown
                precision, a size that is not a multiple of 32 or more ``--threads`` than
                the machine can use (exit 2).
            ValueError: a device this machine does not have (exit 1).
        """
        from deltar.inference.checks import check_backend_options
        from deltar.inference.preprocess import check_input_size
        from deltar.io.resources import check_threads

        chosen = [f"--{kind}" for kind in ("preset", "checkpoint", "official", "onnx")
                  if getattr(self, kind) is not None]
        if len(chosen) > 1:
            raise typer.BadParameter("give only one of --preset, --checkpoint, --official, "
                                     f"--onnx (got {chosen})")
        size = parse_size(self.size)
        try:  # the library's own checks, named as the options
            check_backend_options(self.precision, self.flip, self.onnx is not None,
                                  names=("--precision", "--flip"))
            if size is not None:
                check_input_size(size, "--size")
            if self.threads is not None:
                check_threads(self.threads, "--threads")
        except ValueError as err:
            raise typer.BadParameter(str(err)) from err
        if self.onnx is None and self.device != "cpu":  # the CPU is there: no torch import
            from deltar.cli.checks import torch_device

            torch_device(self.device)

    def load(self) -> DepthEstimator:
        """Check, then build the estimator; a preset's random weights get a warning line."""
        from deltar.cli.errors import warn
        from deltar.inference.checks import InputSizeError
        from deltar.inference.loading import load_estimator

        self.check()
        source, kind = self.source()
        if source is None:
            from deltar.weights import bundled_model_names

            if "default" not in bundled_model_names():
                raise typer.BadParameter("this installation has no bundled model; give one "
                                         "of --preset, --checkpoint, --official, --onnx")
        with warnings.catch_warnings():
            if kind == "preset":  # said once, below, in the CLI's words
                warnings.simplefilter("ignore", UserWarning)
            try:
                estimator = load_estimator(source, kind=kind, device=self.device,
                                           precision=self.precision,
                                           input_size=parse_size(self.size),
                                           threads=self.threads, flip_average=self.flip,
                                           **({"blend": None} if self.network_only else {}),
                                           **({"no_target_min_neighbour_m": None}
                                              if self.no_inferred_flags else {}),
                                           **({"zone_outliers": None}
                                              if self.keep_outlier_zones else {}))
            except InputSizeError as err:  # a size an ONNX file lacks: said as the option
                raise typer.BadParameter(str(err).removeprefix("input_size "),
                                         param_hint="--size") from None
        if kind == "preset":
            warn(f"preset {self.preset!r} has random, untrained weights: its depth is "
                 "meaningless")
        return estimator


#: Placeholder default of a command's ``model`` parameter (the decorator replaces it).
MODEL_OPTIONS = ModelOptions()

#: The typer parameters that stand for a ``model: ModelOptions`` parameter.
_OPTION_TYPES = {"preset": PresetOption, "checkpoint": CheckpointOption,
                 "official": OfficialOption, "onnx": OnnxOption, "device": DeviceOption,
                 "precision": PrecisionOption, "size": SizeOption, "threads": ThreadsOption,
                 "flip": FlipOption, "network_only": NetworkOnlyOption,
                 "no_inferred_flags": KeepUnflaggedOption,
                 "keep_outlier_zones": KeepOutliersOption}
_MODEL_GROUP = option_group("model", ModelOptions, _OPTION_TYPES)


def model_options(command):
    """Replace the command's ``model: ModelOptions`` parameter by the twelve model options.

    The options appear where ``model`` stands in the signature; the command receives
    ``model=ModelOptions(...)`` (:func:`~deltar.cli.option_groups.option_group`).
    """
    return _MODEL_GROUP(command)
