"""``deltar predict``, ``record``, ``replay``, ``wall-test`` and ``export``."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from deltar.cli.main import app
from deltar.cli.model_options import (
    MODEL_OPTIONS,
    CheckpointOption,
    ModelOptions,
    OfficialOption,
    PresetOption,
    model_options,
    parse_size,
)
from deltar.cli.robotics import (
    BagOption,
    BagStorageOption,
    ImageTopicOption,
    InfoTopicOption,
    OutBagOption,
    PointsOption,
    RerunOption,
    RerunSaveOption,
    TofFormatOption,
    TofOrientationOption,
    TofSigmaOption,
    TofTopicOption,
    TopicPrefixOption,
)
from deltar.io.file_pairs import pair_by_stem

_DEFAULT_OUTPUTS = "png16,npy,color,ply,panel"

CalibOption = typer.Option(None, "--calib", help="Rig calibration JSON (deltar calibrate).")
AllowNoZonesOption = typer.Option(False, "--allow-no-zones", help="Write frames without "
                                  "any valid zone as image-only estimates (flagged; metric "
                                  "scale unknown) instead of refusing them.")


def _fail(err: Exception) -> None:
    from deltar.cli.errors import fail

    fail(err)


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


@app.command("predict")
@model_options
def predict_command(
    image: Path | None = typer.Option(None, "--image", help="One RGB image."),
    zones: Path | None = typer.Option(None, "--zones", help="Its zone frame (.json/.npz, or "
                                      "a raw driver dump .json)."),
    images: Path | None = typer.Option(None, "--images", help="Folder of images (folder "
                                       "mode, paired with --zones-dir by file stem)."),
    zones_dir: Path | None = typer.Option(None, "--zones-dir", help="Folder of zone frames."),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    calib: Path | None = CalibOption,
    model: ModelOptions = MODEL_OPTIONS,
    outputs: str = typer.Option(_DEFAULT_OUTPUTS, help="Comma list of png16 (uint16 mm), "
                                "npy (float32 m), color, ply (point cloud), panel."),
    overwrite: bool = typer.Option(False, help="Replace existing outputs (never inputs)."),
    skip_existing: bool = typer.Option(False, "--skip-existing", help="Resume: keep the "
                                       "outputs that exist, write only the missing ones."),
    keep_going: bool = typer.Option(False, "--keep-going", help="Folder mode: report a "
                                    "frame that fails and go on; the summary counts the "
                                    "failures (exit code 1 if any)."),
    allow_no_zones: bool = AllowNoZonesOption,
    rerun: bool = RerunOption,
    rerun_save: Path | None = RerunSaveOption,
) -> None:
    """Predict dense metric depth from RGB image(s) and ToF zone frame(s).

    Inputs, calibration and outputs are checked before the network is built.
    """
    from deltar.cli.checks import output_folder
    from deltar.cli.errors import warn
    from deltar.cli.jobs import no_zone_message, plan_jobs, run_jobs
    from deltar.cli.progress import ProgressReport
    from deltar.cli.robotics import open_viewer

    single = image is not None or zones is not None
    folder = images is not None or zones_dir is not None
    if single == folder or (single and (image is None or zones is None)) or \
            (folder and (images is None or zones_dir is None)):
        raise typer.BadParameter("give --image and --zones, or --images and --zones-dir")
    if overwrite and skip_existing:
        raise typer.BadParameter("give --overwrite or --skip-existing, not both")
    kinds = _parse_outputs(outputs)
    model.check()
    first = None
    if single:
        from deltar.data.rgbd import read_color
        from deltar.io.zone_file import load_zone_frame

        pairs, unpaired = [(image, zones)], []
        first = (read_color(image), load_zone_frame(zones))
        if first[1].valid_count == 0 and not allow_no_zones:
            raise ValueError(no_zone_message(zones, first[1]))
    else:
        pairs, unpaired = pair_by_stem(images, zones_dir)
        if not pairs:
            raise ValueError(f"no image in {images} has a zone file with the same stem in "
                             f"{zones_dir}")
    output_folder(out, "--out")
    jobs, complete = plan_jobs(pairs, out, kinds, overwrite=overwrite,
                               skip_existing=skip_existing)
    calibration = _load_calibration(calib)
    if first is not None:
        from deltar.inference.preprocess import check_image

        check_image(first[0], str(image))
        shape = first[0].shape[:2]
        if calibration is not None and shape != (calibration.intrinsics.height,
                                                 calibration.intrinsics.width):
            intr = calibration.intrinsics
            raise ValueError(f"{image} is {shape[0]}x{shape[1]} pixels but --calib {calib} is "
                             f"for the calibrated resolution {intr.height}x{intr.width}; "
                             "resize the image or recalibrate")
    if unpaired:
        warn(f"{len(unpaired)} files without a partner are left out: "
             f"{unpaired[:5]}{' ...' if len(unpaired) > 5 else ''}")
    if complete:
        typer.echo(f"{complete} frame(s) already have every output (--skip-existing)")
    if not jobs:
        typer.echo(f"nothing to do: every output exists in {out}")
        return
    estimator = model.load()
    viewer = open_viewer(rerun, rerun_save)

    def show(rgb, prediction) -> None:
        viewer.log_prediction(rgb, prediction, calibration=calibration,
                              fov_deg=estimator.fov_deg)

    with ProgressReport("predicting", total=len(jobs),
                        terminal=None if len(jobs) > 1 else False) as progress:
        summary = run_jobs(jobs, estimator, out, calibration=calibration,
                           overwrite=overwrite, keep_going=keep_going,
                           allow_no_zones=allow_no_zones,
                           progress=progress if len(jobs) > 1 else None,
                           first=first if first is not None and jobs else None,
                           on_prediction=None if viewer is None else show)
    if viewer is not None:
        viewer.close()
    typer.echo(f"wrote {summary.written} prediction(s) to {out}"
               + (f" ({summary.image_only} image-only)" if summary.image_only else ""))
    if summary.failed:
        from deltar.cli.errors import fail

        fail(f"{len(summary.failed)} of {len(jobs)} frames failed (first: "
             f"{summary.failed[0][0]}: {summary.failed[0][1]}); re-run with --skip-existing "
             "after fixing them")


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
    frames: int | None = typer.Option(None, min=1, help="Stop after this many camera "
                                      "frames."),
    duration: float | None = typer.Option(None, help="Stop after this many seconds."),
    sensor_hz: float = typer.Option(15.0, help="Sensor rate (simulated mode)."),
    bag: bool = typer.Option(False, "--bag", help="Write OUT as a new ROS 2 bag (camera "
                             "Image + CameraInfo, depth, deltar_msgs/msg/ZoneFrame)."),
    bag_storage: str = BagStorageOption,
    rerun: bool = RerunOption,
    rerun_save: Path | None = RerunSaveOption,
) -> None:
    """Record camera frames and ToF zone frames with timestamps into a recording folder."""
    from deltar.capture.drivers import (
        HardwareRig,
        OpenCVCamera,
        SimulatedRig,
        open_sparkfun,
        open_vl53l5cx_ctypes,
    )
    from deltar.capture.record import record
    from deltar.cli.checks import finite, output_folder
    from deltar.cli.progress import ProgressReport
    from deltar.cli.robotics import CaptureLogger, open_viewer
    from deltar.data.sources import open_source

    if grid not in (4, 8):
        raise typer.BadParameter(f"must be 4 or 8, got {grid}", param_hint="--grid")
    finite(sensor_hz, "--sensor-hz", positive=True)
    if duration is not None:
        finite(duration, "--duration", positive=True)
    output_folder(out, "OUT")
    try:
        intrinsics = None
        if simulate is not None:
            rig = SimulatedRig(open_source(simulate), grid=grid, sensor_hz=sensor_hz)
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
        viewer = open_viewer(rerun, rerun_save)
        with ProgressReport("recording", total=total, unit="images") as progress:
            summary = record(out, rig, max_frames=frames, duration_s=duration,
                             intrinsics=intrinsics,
                             on_step=lambda s: progress.update(s.images),
                             bag_storage=bag_storage if bag else None,
                             on_capture=None if viewer is None else CaptureLogger(viewer))
        if viewer is not None:
            viewer.close()
    except (ValueError, FileNotFoundError, FileExistsError, ImportError) as err:
        _fail(err)
    typer.echo(f"recorded {summary.images} images, {summary.zone_frames} zone frames, "
               f"{summary.depth_maps} depth maps over {summary.duration_s:.2f} s into {out}")


@app.command("replay")
@model_options
def replay_command(
    recording: Path | None = typer.Argument(None, help="Recording folder (or give --bag)."),
    out: Path | None = typer.Option(None, "--out", help="Output folder (outside the "
                                    "recording)."),
    show: bool = typer.Option(False, help="Show depth live in an OpenCV window instead."),
    calib: Path | None = CalibOption,
    model: ModelOptions = MODEL_OPTIONS,
    outputs: str = typer.Option("png16,npy,color", help="Comma list of output kinds."),
    tolerance: float = typer.Option(0.02, min=0.0, help="Largest image-zone time offset, "
                                    "seconds."),
    time_offset: float | None = typer.Option(None, "--time-offset", help="Camera clock minus "
                                             "sensor clock, seconds, applied when pairing "
                                             "(default: the --calib file's, else 0)."),
    every: int = typer.Option(1, min=1, help="Use every N-th frame."),
    limit: int | None = typer.Option(None, min=1, help="Stop after this many frames."),
    overwrite: bool = typer.Option(False, help="Replace existing outputs."),
    allow_no_zones: bool = AllowNoZonesOption,
    bag: Path | None = BagOption,
    out_bag: Path | None = OutBagOption,
    bag_storage: str = BagStorageOption,
    image_topic: str | None = ImageTopicOption,
    info_topic: str | None = InfoTopicOption,
    tof_topic: str | None = TofTopicOption,
    tof_format: str = TofFormatOption,
    tof_orientation: str = TofOrientationOption,
    tof_sigma: float = TofSigmaOption,
    points: bool = PointsOption,
    topic_prefix: str = TopicPrefixOption,
    rerun: bool = RerunOption,
    rerun_save: Path | None = RerunSaveOption,
) -> None:
    """Pair zone frames with images by nearest timestamp and predict depth for each.

    Frames without any valid zone are skipped with a warning unless --allow-no-zones.
    """
    from deltar.capture.replay import replay, replay_to_folder
    from deltar.cli.progress import ProgressReport
    from deltar.cli.robotics import ReplayViewer, open_viewer, replay_bag_command

    if (recording is None) == (bag is None):
        raise typer.BadParameter("give a RECORDING folder or --bag BAG")
    if bag is not None:
        model.check()
        try:
            typer.echo(replay_bag_command(
                bag, model.load,
                _load_calibration(calib), out=out, show=show, out_bag=out_bag,
                storage=bag_storage, topics=(image_topic, info_topic, tof_topic),
                tof=(tof_format, tof_orientation, tof_sigma), points=points,
                prefix=topic_prefix, rerun=rerun, rerun_save=rerun_save,
                tolerance=tolerance, every=every, limit=limit))
        except (ValueError, FileNotFoundError, FileExistsError, ImportError) as err:
            _fail(err)
        return
    viewing = rerun or rerun_save is not None
    if (out is not None and show) or (out is None and not show and not viewing):
        raise typer.BadParameter("give --out DIR, or --show (and/or --rerun, --rerun-save)")
    kinds = _parse_outputs(outputs)
    model.check()
    calibration = _load_calibration(calib)
    if time_offset is None:
        time_offset = calibration.time_offset_s if calibration is not None else 0.0
    elif not math.isfinite(time_offset):
        raise typer.BadParameter(f"must be finite, got {time_offset}", param_hint="--time-offset")
    total = _check_replay(recording, out, kinds, (tolerance, time_offset), every, limit,
                          overwrite, show)
    estimator = model.load()
    viewer = ReplayViewer(open_viewer(rerun, rerun_save), recording, calibration)
    if out is None:
        items = map(viewer, replay(recording, estimator, calibration=calibration,
                                   tolerance_s=tolerance, time_offset_s=time_offset,
                                   every=every, limit=limit,
                                   skip_no_zones=not allow_no_zones))
        if show:
            _show_live(items)
        else:
            for _ in items:
                pass
        viewer.close()
        return
    with ProgressReport("replaying", total=total) as progress:

        def each(item) -> None:
            viewer(item)
            progress.advance()

        written = replay_to_folder(recording, estimator, out, kinds=kinds,
                                   calibration=calibration, tolerance_s=tolerance,
                                   time_offset_s=time_offset, every=every, limit=limit,
                                   overwrite=overwrite,
                                   on_item=each, skip_no_zones=not allow_no_zones)
    viewer.close()
    typer.echo(f"wrote {len(written)} files to {out}")


def _check_replay(recording: Path, out: Path | None, kinds, pairing: tuple[float, float],
                  every: int, limit: int | None, overwrite: bool, show: bool) -> int:
    """Check a replay's recording and outputs before the model; return its frame count.

    ``pairing`` is (tolerance, time offset) in seconds.
    """
    import warnings

    from deltar.cli.checks import display, existing_outputs, output_folder
    from deltar.inference.outputs import OUTPUT_KINDS
    from deltar.io.recording import Recording

    if show:
        display("--show")
    rec = Recording(recording)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # replaying warns about skipped frames itself
        selected = rec.pairs(tolerance_s=pairing[0], time_offset_s=pairing[1])[::every][:limit]
    if out is not None:
        resolved = out.resolve()
        if resolved == rec.folder.resolve() or rec.folder.resolve() in resolved.parents:
            raise ValueError(f"--out {out} is inside the recording {rec.folder}; choose a "
                             "folder outside it")
        output_folder(out, "--out")
        if not overwrite:
            existing_outputs(out / f"{p.color_path.stem}{OUTPUT_KINDS[k]}" for p in selected
                             for k in kinds)
    return len(selected)


def _show_live(items) -> None:
    import cv2
    import numpy as np

    from deltar.inference.outputs import colorize

    for item in items:  # the display was checked before the model was built
        depth = colorize(item.prediction.depth_m, 0.0, 5.0)
        panel = np.concatenate([item.image, depth], axis=1)
        cv2.imshow("deltar replay", cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
        if cv2.waitKey(1) & 0xFF in (ord("q"), 27):
            break
    cv2.destroyAllWindows()


@app.command("wall-test")
@model_options
def wall_test_command(
    recordings: list[Path] = typer.Argument(..., help="Recordings facing a flat wall, one "
                                            "per distance."),
    out: Path = typer.Option(..., "--out", help="Folder for wall_test.json/.csv/.png."),
    calib: Path | None = CalibOption,
    model: ModelOptions = MODEL_OPTIONS,
    every: int = typer.Option(1, min=1, help="Use every N-th frame."),
    limit: int | None = typer.Option(None, min=1, help="Frames per recording at most."),
    overwrite: bool = typer.Option(False, help="Replace existing result files."),
) -> None:
    """Bias and jitter against a robust plane fit, per distance, network vs raw zones."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from deltar.cli.checks import output_folder
    from deltar.evaluation.wall_test import wall_test, write_results
    from deltar.io.recording import Recording

    model.check()
    for folder in recordings:
        Recording(folder)  # a missing or corrupt recording fails before the model
    output_folder(out, "--out")
    try:
        estimator = model.load()
        results = wall_test(recordings, estimator, calibration=_load_calibration(calib),
                            every=every, limit=limit)
        paths = write_results(out, results, title=estimator.weights, overwrite=overwrite)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        _fail(err)
    table = Table(title=escape(f"flat wall ({estimator.weights})"))
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
    from deltar.capture.replay import recording_calibration
    from deltar.inference.preprocess import scale_rects
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
    preset: PresetOption = None,
    checkpoint: CheckpointOption = None,
    official: OfficialOption = None,
    format: str = typer.Option("onnx", "--format", help="Export format (onnx)."),
    size: str = typer.Option("480x640", "--size", help="Camera image size HxW; the file's "
                             "fixed network input follows the size rule (aspect kept, the "
                             "weights' design pixel count, sides rounded to multiples of "
                             "32; docs/inference.md)."),
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
    from deltar.cli.checks import output_file
    from deltar.export.onnx import export_onnx
    from deltar.export.quantize import export_int8

    if format != "onnx":
        raise typer.BadParameter(f"must be onnx, got {format!r}", param_hint="--format")
    height, width = parse_size(size)
    output_file(out, "--out", overwrite)
    if layout_from is not None and not layout_from.exists():
        raise FileNotFoundError(f"--layout-from {layout_from}: no such calibration file or "
                                "recording folder")
    if int8 != (calibration is not None):
        raise typer.BadParameter("--int8 and --calibration DIR go together",
                                 param_hint="--calibration")
    try:
        estimator = ModelOptions(preset=preset, checkpoint=checkpoint,
                                 official=official).load()
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
    from deltar.export.onnx import export_input_size

    net_h, net_w = export_input_size(estimator.model, height, width)
    typer.echo(f"wrote {path} ({kind}, camera {height}x{width}, network {net_h}x{net_w}, "
               f"weights: {estimator.weights})")
