"""``deltar predict``, ``record``, ``replay``, ``wall-test`` and ``export``."""

from __future__ import annotations

from pathlib import Path

import typer

from deltar.cli.main import app

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm")
_ZONE_SUFFIXES = (".json", ".npz")
_DEFAULT_OUTPUTS = "png16,npy,color,ply,panel"

PresetOption = typer.Option(None, "--preset", help="Model preset (RANDOM weights: for "
                            "testing the pipeline only).")
CheckpointOption = typer.Option(None, "--checkpoint", help="deltar checkpoint (.pt) or a "
                                "bundled model name; the bundled 'default' model when no "
                                "model option is given.")
OfficialOption = typer.Option(None, "--official", help="Officially released weights "
                              "(e.g. nyu.pt).")
OnnxOption = typer.Option(None, "--onnx", help="ONNX model from 'deltar export' "
                          "(onnxruntime backend).")
DeviceOption = typer.Option("cpu", help="Torch device (PyTorch backend).")
PrecisionOption = typer.Option("float32", help="float32, float16 or bfloat16 (PyTorch).")
SizeOption = typer.Option(None, "--size", help="Network input size HxW (multiples of 32); "
                          "default: the image size rounded to multiples of 32.")
ThreadsOption = typer.Option(None, "--threads", help="CPU threads (torch / onnxruntime).")
FlipOption = typer.Option(False, "--flip", help="Test-time flip averaging: also run the "
                          "mirrored image and zones and average (2x network time; "
                          "PyTorch backends).")
CalibOption = typer.Option(None, "--calib", help="Rig calibration JSON (deltar calibrate).")


def _fail(err: Exception) -> None:
    from rich.console import Console

    Console(stderr=True).print(f"[red]error:[/red] {err}")
    raise typer.Exit(1)


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError as err:
        raise typer.BadParameter(f"size must look like 480x640, got {text!r}") from err
    return height, width


def _build_estimator(preset, checkpoint, official, onnx, device, precision, size, threads,
                     flip=False):
    import torch

    from deltar.inference.estimator import DepthEstimator

    chosen = [name for name, value in (("--preset", preset), ("--checkpoint", checkpoint),
                                       ("--official", official), ("--onnx", onnx))
              if value is not None]
    if not chosen:
        # No model named: the model bundled with the package.
        from deltar.weights import bundled_model_names

        if "default" not in bundled_model_names():
            raise typer.BadParameter("this installation has no bundled model; give one of "
                                     "--preset, --checkpoint, --official, --onnx")
        checkpoint, chosen = "default", ["--checkpoint"]
    if len(chosen) != 1:
        raise typer.BadParameter("give only one of --preset, --checkpoint, --official, "
                                 f"--onnx (got {chosen})")
    if threads:
        torch.set_num_threads(int(threads))
    kwargs = {"input_size": _parse_size(size)}
    if flip:
        if onnx is not None:
            raise typer.BadParameter("--flip needs a PyTorch model (an ONNX file is fixed to "
                                     "one zone layout)", param_hint="--flip")
        kwargs["flip_average"] = True
    if onnx is not None:
        return DepthEstimator.from_onnx(onnx, num_threads=threads, **kwargs)
    kwargs.update(device=device, precision=precision)
    if checkpoint is not None:
        return DepthEstimator.from_checkpoint(checkpoint, **kwargs)
    if official is not None:
        return DepthEstimator.from_official(official, **kwargs)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        estimator = DepthEstimator.from_preset(preset, **kwargs)
    from rich.console import Console

    Console(stderr=True).print(f"[yellow]warning:[/yellow] preset {preset!r} has random, "
                               "untrained weights: its depth is meaningless")
    return estimator


def _load_calibration(path: Path | None):
    if path is None:
        return None
    from deltar.calibration.rig import RigCalibration

    return RigCalibration.load(path)


def _parse_outputs(text: str) -> tuple[str, ...]:
    from deltar.inference.outputs import OUTPUT_KINDS

    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    unknown = [k for k in kinds if k not in OUTPUT_KINDS]
    if unknown or not kinds:
        raise typer.BadParameter(f"--outputs must be a comma list of {list(OUTPUT_KINDS)}, "
                                 f"got {text!r}")
    return kinds


def pair_by_stem(images_dir: Path, zones_dir: Path) -> tuple[list[tuple[Path, Path]], list[str]]:
    """Pair image files and zone files by file stem.

    Returns:
        (pairs sorted by stem, stems that have only an image or only a zone file).
    """
    for folder, name in ((images_dir, "--images"), (zones_dir, "--zones-dir")):
        if not folder.is_dir():
            raise FileNotFoundError(f"{name} folder not found: {folder}")
    images = {p.stem: p for p in images_dir.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES}
    zones = {p.stem: p for p in zones_dir.iterdir() if p.suffix.lower() in _ZONE_SUFFIXES}
    stems = sorted(images.keys() & zones.keys())
    unpaired = sorted(images.keys() ^ zones.keys())
    return [(images[s], zones[s]) for s in stems], unpaired


@app.command("predict")
def predict_command(
    image: Path | None = typer.Option(None, "--image", help="One RGB image."),
    zones: Path | None = typer.Option(None, "--zones", help="Its zone frame (.json/.npz, or "
                                      "a raw driver dump .json)."),
    images: Path | None = typer.Option(None, "--images", help="Folder of images (folder "
                                       "mode, paired with --zones-dir by file stem)."),
    zones_dir: Path | None = typer.Option(None, "--zones-dir", help="Folder of zone frames."),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    calib: Path | None = CalibOption,
    preset: str | None = PresetOption,
    checkpoint: Path | None = CheckpointOption,
    official: Path | None = OfficialOption,
    onnx: Path | None = OnnxOption,
    device: str = DeviceOption,
    precision: str = PrecisionOption,
    size: str | None = SizeOption,
    threads: int | None = ThreadsOption,
    flip: bool = FlipOption,
    outputs: str = typer.Option(_DEFAULT_OUTPUTS, help="Comma list of png16 (uint16 mm), "
                                "npy (float32 m), color, ply (point cloud), panel."),
    overwrite: bool = typer.Option(False, help="Replace existing outputs (never inputs)."),
) -> None:
    """Predict dense metric depth from RGB image(s) and ToF zone frame(s)."""
    from rich.progress import track

    from deltar.data.rgbd import read_color
    from deltar.inference.outputs import OUTPUT_KINDS, write_prediction
    from deltar.io.zone_file import load_zone_frame

    single = image is not None or zones is not None
    folder = images is not None or zones_dir is not None
    if single == folder or (single and (image is None or zones is None)) or \
            (folder and (images is None or zones_dir is None)):
        raise typer.BadParameter("give --image and --zones, or --images and --zones-dir")
    kinds = _parse_outputs(outputs)
    try:
        if single:
            pairs, unpaired = [(image, zones)], []
        else:
            pairs, unpaired = pair_by_stem(images, zones_dir)
            if not pairs:
                raise ValueError(f"no image in {images} has a zone file with the same stem in "
                                 f"{zones_dir}")
        inputs = {p.resolve() for pair in pairs for p in pair}
        for img_path, _ in pairs:
            for kind in kinds:
                target = (out / f"{img_path.stem}{OUTPUT_KINDS[kind]}").resolve()
                if target in inputs:
                    raise ValueError(f"output {target} would overwrite an input file")
        estimator = _build_estimator(preset, checkpoint, official, onnx, device, precision,
                                     size, threads, flip)
        calibration = _load_calibration(calib)
        for img_path, zone_path in track(pairs, description="predicting",
                                         disable=len(pairs) < 2):
            rgb = read_color(img_path)
            frame = load_zone_frame(zone_path)
            prediction = estimator.predict(rgb, frame, calibration)
            write_prediction(out, img_path.stem, rgb, prediction, kinds=kinds,
                             overwrite=overwrite,
                             title=f"{img_path.name} ({estimator.weights})")
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        _fail(err)
    if unpaired:
        typer.echo(f"warning: {len(unpaired)} files without a partner were skipped: "
                   f"{unpaired[:5]}{' ...' if len(unpaired) > 5 else ''}", err=True)
    typer.echo(f"wrote {len(pairs)} prediction(s) to {out}")


def _simulated_source(spec: str):
    """'wall:<metres>[:<frames>[:<H>x<W>]]' or any deltar.data.sources spec."""
    from deltar.inference.wall_test import FlatWallSource

    if spec.startswith("wall:"):
        parts = spec[len("wall:"):].split(":")
        try:
            distance = float(parts[0])
            frames = int(parts[1]) if len(parts) > 1 else 10
            height, width = (int(v) for v in parts[2].split("x")) if len(parts) > 2 \
                else (240, 320)
        except (ValueError, IndexError) as err:
            raise ValueError(f"wall source must look like 'wall:1.5', 'wall:1.5:20' or "
                             f"'wall:1.5:20:240x320', got {spec!r}") from err
        return FlatWallSource(distance, frames, height, width)
    from deltar.data.sources import open_source

    return open_source(spec)


@app.command("record")
def record_command(
    out: Path = typer.Argument(..., help="Recording folder (new, or a recording of the same "
                               "rig to append to)."),
    simulate: str | None = typer.Option(None, help="No hardware: play this RGB-D source as "
                                        "camera + simulated sensor ('procedural:20', an "
                                        "RGB-D folder, or 'wall:<m>[:<frames>[:<H>x<W>]]')."),
    camera: int = typer.Option(0, help="OpenCV camera index (hardware mode)."),
    sensor: str = typer.Option("vl53l5cx-ctypes", help="Driver: vl53l5cx-ctypes or sparkfun "
                               "(hardware mode)."),
    calib: Path | None = typer.Option(None, "--calib", help="Rig calibration giving the "
                                      "camera intrinsics (hardware mode)."),
    grid: int = typer.Option(8, help="Zones per side (4 or 8)."),
    frames: int | None = typer.Option(None, help="Stop after this many camera frames."),
    duration: float | None = typer.Option(None, help="Stop after this many seconds."),
    sensor_hz: float = typer.Option(15.0, help="Sensor rate (simulated mode)."),
) -> None:
    """Record camera frames and ToF zone frames with timestamps into a recording folder."""
    from rich.progress import Progress

    from deltar.inference.drivers import (
        HardwareRig,
        OpenCVCamera,
        SimulatedRig,
        open_sparkfun,
        open_vl53l5cx_ctypes,
    )
    from deltar.inference.record import record

    try:
        intrinsics = None
        if simulate is not None:
            rig = SimulatedRig(_simulated_source(simulate), grid=grid, sensor_hz=sensor_hz)
        else:
            calibration = _load_calibration(calib)
            if calibration is None:
                raise ValueError("hardware recording needs --calib for the camera intrinsics")
            intrinsics = calibration.intrinsics
            openers = {"vl53l5cx-ctypes": open_vl53l5cx_ctypes, "sparkfun": open_sparkfun}
            if sensor not in openers:
                raise ValueError(f"--sensor must be one of {sorted(openers)}, got {sensor!r}")
            rig = HardwareRig(OpenCVCamera(camera, (intrinsics.height, intrinsics.width)),
                              openers[sensor](grid=grid))
        total = frames or (len(rig.source) if simulate is not None else None)
        with Progress(transient=True) as progress:
            task = progress.add_task("recording", total=total)
            summary = record(out, rig, max_frames=frames, duration_s=duration,
                             intrinsics=intrinsics,
                             on_step=lambda s: progress.update(task, completed=s.images))
    except (ValueError, FileNotFoundError, FileExistsError, ImportError) as err:
        _fail(err)
    typer.echo(f"recorded {summary.images} images, {summary.zone_frames} zone frames, "
               f"{summary.depth_maps} depth maps over {summary.duration_s:.2f} s into {out}")


@app.command("replay")
def replay_command(
    recording: Path = typer.Argument(..., help="Recording folder."),
    out: Path | None = typer.Option(None, "--out", help="Output folder (outside the "
                                    "recording)."),
    show: bool = typer.Option(False, help="Show depth live in an OpenCV window instead."),
    calib: Path | None = CalibOption,
    preset: str | None = PresetOption,
    checkpoint: Path | None = CheckpointOption,
    official: Path | None = OfficialOption,
    onnx: Path | None = OnnxOption,
    device: str = DeviceOption,
    precision: str = PrecisionOption,
    size: str | None = SizeOption,
    threads: int | None = ThreadsOption,
    flip: bool = FlipOption,
    outputs: str = typer.Option("png16,npy,color", help="Comma list of output kinds."),
    tolerance: float = typer.Option(0.02, help="Largest image-zone time offset, seconds."),
    every: int = typer.Option(1, help="Use every N-th frame."),
    limit: int | None = typer.Option(None, help="Stop after this many frames."),
    overwrite: bool = typer.Option(False, help="Replace existing outputs."),
) -> None:
    """Pair zone frames with images by nearest timestamp and predict depth for each."""
    from rich.progress import Progress

    from deltar.inference.replay import replay, replay_to_folder

    if (out is None) == (not show):
        raise typer.BadParameter("give --out DIR, or --show")
    kinds = _parse_outputs(outputs)
    try:
        estimator = _build_estimator(preset, checkpoint, official, onnx, device, precision,
                                     size, threads, flip)
        calibration = _load_calibration(calib)
        if show:
            _show_live(replay(recording, estimator, calibration=calibration,
                              tolerance_s=tolerance, every=every, limit=limit))
            return
        with Progress(transient=True) as progress:
            task = progress.add_task("replaying", total=None)
            written = replay_to_folder(recording, estimator, out, kinds=kinds,
                                       calibration=calibration, tolerance_s=tolerance,
                                       every=every, limit=limit, overwrite=overwrite,
                                       on_item=lambda _: progress.advance(task))
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        _fail(err)
    typer.echo(f"wrote {len(written)} files to {out}")


def _show_live(items) -> None:
    import cv2
    import numpy as np

    from deltar.inference.outputs import colorize

    for item in items:
        depth = colorize(item.prediction.depth_m, 0.0, 5.0)
        panel = np.concatenate([item.image, depth], axis=1)
        cv2.imshow("deltar replay", cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
        if cv2.waitKey(1) & 0xFF in (ord("q"), 27):
            break
    cv2.destroyAllWindows()


@app.command("wall-test")
def wall_test_command(
    recordings: list[Path] = typer.Argument(..., help="Recordings facing a flat wall, one "
                                            "per distance."),
    out: Path = typer.Option(..., "--out", help="Folder for wall_test.json/.csv/.png."),
    calib: Path | None = CalibOption,
    preset: str | None = PresetOption,
    checkpoint: Path | None = CheckpointOption,
    official: Path | None = OfficialOption,
    onnx: Path | None = OnnxOption,
    device: str = DeviceOption,
    precision: str = PrecisionOption,
    size: str | None = SizeOption,
    threads: int | None = ThreadsOption,
    every: int = typer.Option(1, help="Use every N-th frame."),
    limit: int | None = typer.Option(None, help="Frames per recording at most."),
    overwrite: bool = typer.Option(False, help="Replace existing result files."),
) -> None:
    """Bias and jitter against a robust plane fit, per distance, network vs raw zones."""
    from rich.console import Console
    from rich.table import Table

    from deltar.inference.wall_test import wall_test, write_results

    try:
        estimator = _build_estimator(preset, checkpoint, official, onnx, device, precision,
                                     size, threads)
        results = wall_test(recordings, estimator, calibration=_load_calibration(calib),
                            every=every, limit=limit)
        paths = write_results(out, results, title=estimator.weights, overwrite=overwrite)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        _fail(err)
    table = Table(title=f"flat wall ({estimator.weights})")
    for column in ("distance m", "frames", "plane from", "net bias mm", "net jitter mm",
                   "zones bias mm", "zones jitter mm"):
        table.add_column(column, justify="right")
    for r in results:
        table.add_row(f"{r.distance_m:.3f}", str(r.frames), r.reference,
                      f"{1000 * r.network_bias_m:.1f}", f"{1000 * r.network_jitter_m:.1f}",
                      f"{1000 * r.zones_bias_m:.1f}", f"{1000 * r.zones_jitter_m:.1f}")
    Console().print(table)
    typer.echo(f"wrote {', '.join(str(p) for p in paths.values())}")


def _layout_rects(source: Path, height: int, width: int):
    """Zone rectangles in pixels of a height x width image from a calibration or recording."""
    from deltar.calibration.rig import RigCalibration
    from deltar.inference.estimator import scale_rects
    from deltar.inference.replay import recording_calibration
    from deltar.io.recording import Recording

    if source.is_dir():
        calibration = recording_calibration(Recording(source))
    else:
        calibration = RigCalibration.load(source)
    intr = calibration.intrinsics
    # Zones placed at 2 m; with parallax, other distances may need their own export.
    rects = calibration.zone_rects_for(2.0, (intr.height, intr.width))
    return scale_rects(rects, (intr.height, intr.width), (height, width))


@app.command("export")
def export_command(
    out: Path = typer.Option(..., "--out", help="Output file (.onnx)."),
    preset: str | None = PresetOption,
    checkpoint: Path | None = CheckpointOption,
    official: Path | None = OfficialOption,
    format: str = typer.Option("onnx", "--format", help="Export format (onnx)."),
    size: str = typer.Option("480x640", "--size", help="Camera image size HxW; the model's "
                             "fixed input is that rounded to multiples of 32."),
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
    from deltar.export.onnx import export_onnx
    from deltar.export.quantize import export_int8

    if format != "onnx":
        raise typer.BadParameter(f"--format must be onnx, got {format!r}")
    height, width = _parse_size(size)
    if int8 != (calibration is not None):
        raise typer.BadParameter("--int8 and --calibration DIR go together",
                                 param_hint="--calibration")
    try:
        estimator = _build_estimator(preset, checkpoint, official, None, "cpu", "float32",
                                     None, None)
        rects = None if layout_from is None else _layout_rects(layout_from, height, width)
        metadata = {"deltar_weights": estimator.weights}
        if int8:
            path = export_int8(estimator.model, out, height, width, calibration,
                               frames=calibration_frames, zone_rects=rects,
                               overwrite=overwrite, metadata=metadata)
        else:
            path = export_onnx(estimator.model, out, height, width, zone_rects=rects,
                               overwrite=overwrite, metadata=metadata)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        _fail(err)
    kind = "int8" if int8 else "float32"
    typer.echo(f"wrote {path} ({kind}, {height}x{width}, weights: {estimator.weights})")
