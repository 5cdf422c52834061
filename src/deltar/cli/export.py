"""``deltar export``: a model to an ONNX file (float32 or int8)."""

from __future__ import annotations

from pathlib import Path

import typer

from deltar.cli.errors import fail
from deltar.cli.model_options import (
    CheckpointOption,
    ModelOptions,
    OfficialOption,
    PresetOption,
)


def _layout_rects(source: Path, height: int, width: int):
    """Zone rectangles in pixels of a height x width image from a calibration or recording."""
    from deltar.calibration.rig import RigCalibration
    from deltar.capture.replay import recording_calibration
    from deltar.inference.preprocess import scale_rects
    from deltar.io.recording import Recording

    try:
        calibration = recording_calibration(Recording(source)) if source.is_dir() \
            else RigCalibration.load(source)
    except (ValueError, FileNotFoundError) as err:
        raise ValueError(f"--layout-from: {err}") from err
    intr = calibration.intrinsics
    if abs(intr.width / intr.height - width / height) > 0.01 * width / height:
        from deltar.cli.errors import warn

        warn(f"--layout-from {source} is for {intr.height}x{intr.width} images, whose aspect "
             f"differs from --size {height}x{width}: the zone layout is stretched with the "
             "images; export at the camera's aspect (e.g. --size "
             f"{height}x{round(height * intr.width / intr.height / 32) * 32}) unless "
             "stretching is meant")
    # Zones placed at 2 m; with parallax, other distances may need their own export.
    rects = calibration.zone_rects_for(2.0, (intr.height, intr.width))
    return scale_rects(rects, (intr.height, intr.width), (height, width))


def export_command(
    out: Path = typer.Option(..., "--out", help="Output file (.onnx)."),
    preset: PresetOption = None,
    checkpoint: CheckpointOption = None,
    official: OfficialOption = None,
    format: str = typer.Option("onnx", "--format", help="Export format (onnx)."),
    size: str = typer.Option("480x640", "--size", help="Camera image size HxW; the file's "
                             "fixed network input follows the size rule (aspect kept, the "
                             "weights' design pixel count, sides rounded to multiples of "
                             "32; docs/inference.md). Several, comma-separated: one file "
                             "per network size (OUT, then OUT's stem.HxW.onnx beside it), "
                             "sharing one weights file (OUT.data)."),
    layout_from: Path | None = typer.Option(None, "--layout-from", help="Fix the zone "
                                            "layout from a rig calibration JSON or a "
                                            "recording folder (default: nominal 8x8)."),
    int8: bool = typer.Option(False, "--int8", help="Write a statically quantised int8 "
                              "model (see docs/inference.md for its measured accuracy)."),
    calibration: Path | None = typer.Option(None, "--calibration", help="RGB-D folder whose "
                                            "frames (zones simulated) calibrate --int8."),
    calibration_frames: int = typer.Option(16, "--calibration-frames", min=1,
                                           help="Calibration frames for --int8."),
    overwrite: bool = typer.Option(False, help="Replace an existing file."),
) -> None:
    """Export a model to ONNX (dynamic batch, fixed input size and zone layout)."""
    from deltar.extras import require_extra

    for module in ("onnx", "torch"):  # one line naming the 'export' extra
        require_extra(module, "deltar export", "export")
    from deltar.cli.checks import output_file
    from deltar.export.onnx import export_onnx, export_onnx_sizes, sized_export_paths
    from deltar.export.quantize import export_int8
    from deltar.io.input_file import refuse_input_as_output

    if format != "onnx":
        raise typer.BadParameter(f"must be onnx, got {format!r}", param_hint="--format")
    from deltar.cli.checks import image_size

    sizes = [image_size(text.strip(), "--size") for text in size.split(",")]
    height, width = sizes[0]
    if len(sizes) > 1 and (int8 or layout_from is not None):
        raise typer.BadParameter("several sizes go without --int8 and --layout-from",
                                 param_hint="--size")
    refuse_input_as_output(out, [checkpoint, official, layout_from, calibration], "--out")
    if out.suffix.lower() != ".onnx":  # a .pt name would be read back as a checkpoint
        raise typer.BadParameter(f"{out} must end in .onnx (the file is an ONNX model)",
                                 param_hint="--out")
    output_file(out, "--out", overwrite)
    if len(sizes) > 1:  # the sizes share the weights file beside OUT: checked before the model
        output_file(out.with_name(out.name + ".data"), "--out", overwrite)
    if layout_from is not None and not layout_from.exists():
        raise FileNotFoundError(f"--layout-from {layout_from}: no such calibration file or "
                                "recording folder")
    if int8 != (calibration is not None):
        raise typer.BadParameter("--int8 and --calibration DIR go together",
                                 param_hint="--calibration")
    # A bad --layout-from or --calibration fails before the model is built.
    rects = None if layout_from is None else _layout_rects(layout_from, height, width)
    if calibration is not None:
        from deltar.export.quantize import open_calibration_frames

        try:
            calibration = open_calibration_frames(calibration)
        except (ValueError, FileNotFoundError) as err:
            raise ValueError(f"--calibration: {err}") from err
    try:
        estimator = ModelOptions(preset=preset, checkpoint=checkpoint,
                                 official=official).load()
        metadata = {"deltar_weights": estimator.weights}
        if int8:
            path = export_int8(estimator.model, out, height, width, calibration,
                               frames=calibration_frames, zone_rects=rects,
                               overwrite=overwrite, metadata=metadata)
        elif len(sizes) > 1:
            # The other sizes' names follow the weights' design size: checked once the
            # model is there, before the export.
            for other in sized_export_paths(estimator.model, out, sizes).values():
                refuse_input_as_output(other, [checkpoint, official], "--out")
                output_file(other, "--out", overwrite)
            paths = export_onnx_sizes(estimator.model, out, sizes, overwrite=overwrite,
                                      metadata=metadata)
            path = ", ".join(str(p) for p in paths)
        else:
            path = export_onnx(estimator.model, out, height, width, zone_rects=rects,
                               overwrite=overwrite, metadata=metadata)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        fail(err)
    kind = "int8" if int8 else "float32"
    from deltar.export.onnx import export_input_size

    networks = ", ".join("x".join(map(str, export_input_size(estimator.model, *s)))
                         for s in sizes)
    cameras = ", ".join(f"{h}x{w}" for h, w in sizes)
    typer.echo(f"wrote {path} ({kind}, camera {cameras}, network {networks}, "
               f"weights: {estimator.weights})")
