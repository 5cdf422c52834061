"""``deltar record`` and ``deltar replay``: a rig to a recording, a recording to depth."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from deltar.cli.checks import refuse_unused_options
from deltar.cli.errors import fail, format_error, warn
from deltar.cli.frame_options import (
    AllowNoZonesOption,
    CalibOption,
    check_calibration_fits,
    load_calibration,
    parse_outputs,
)
from deltar.cli.model_options import MODEL_OPTIONS, ModelOptions, model_options
from deltar.cli.robotics import (
    BAG_TOPICS,
    BagOption,
    BagStorageOption,
    BagTopics,
    OutBagOption,
    PointsOption,
    RerunOption,
    RerunSaveOption,
    TopicPrefixOption,
    bag_topic_options,
)

#: ``deltar replay --outputs`` when not given.
DEFAULT_OUTPUTS = "png16,npy,color"
#: Largest depth a recording's 16-bit millimetre depth images hold, metres.
MAX_RECORDED_DEPTH_M = 65.535


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
    targets: int | None = typer.Option(None, "--targets", min=1, max=4, help="Targets per "
                                       "zone, 1-4 (ST's VL53L5CX_NB_TARGET_PER_ZONE): the "
                                       "simulated sensor reports that many (default 1); a "
                                       "driver reads that many, as its library was built "
                                       "(default: one). Every target is recorded with its "
                                       "return signal."),
    bag: bool = typer.Option(False, "--bag", help="Write OUT as a new ROS 2 bag (camera "
                             "Image + CameraInfo, depth, deltar_msgs/msg/ZoneFrame, or "
                             "MultiTargetZoneFrame with --targets)."),
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
    from deltar.cli.robotics import CaptureLogger, check_viewer, open_viewer
    from deltar.data.sources import open_source

    check_viewer(rerun, rerun_save)  # before the camera and the sensor are opened
    if grid not in (4, 8):
        raise typer.BadParameter(f"must be 4 or 8, got {grid}", param_hint="--grid")
    finite(sensor_hz, "--sensor-hz", positive=True)
    if duration is not None:
        finite(duration, "--duration", positive=True)
    output_folder(out, "OUT")
    if bag and out.exists():
        raise typer.BadParameter(f"{out} exists; with --bag the recording is a new bag, "
                                 "written whole: choose another path", param_hint="OUT")
    if simulate is not None:
        refuse_unused_options({"--camera": camera != 0, "--sensor": sensor != "vl53l5cx-ctypes",
                               "--calib": calib is not None}, "for hardware recording",
                              "with --simulate the RGB-D source is the camera (with its "
                              "intrinsics) and the sensor is simulated")
    if simulate is not None and Path(simulate).exists():
        from deltar.io.input_file import refuse_input_as_output

        refuse_input_as_output(out, [Path(simulate)], "OUT", folder=True)
    from deltar.io.recording import META_FILE, check_recording_folder

    appending = not bag and (out / META_FILE).is_file()
    if not bag:  # before the camera, the sensor and the viewer are opened
        check_recording_folder(out)
        if rerun_save is not None and out.resolve() in rerun_save.resolve().parents:
            raise typer.BadParameter(f"{rerun_save} is inside the recording {out}; write it "
                                     "elsewhere", param_hint="--rerun-save")
    try:
        intrinsics = None
        if simulate is not None:
            try:
                source = open_source(simulate)
                deepest = float(source[0].depth_m.max()) if len(source) else 0.0
            except ValueError as err:
                raise ValueError(f"--simulate {simulate}: {err}") from None
            if deepest > MAX_RECORDED_DEPTH_M:
                raise ValueError(f"--simulate {simulate}: depths up to {deepest:g} m do not fit "
                                 "a recording's depth images (16-bit millimetres, at most "
                                 f"{MAX_RECORDED_DEPTH_M} m)")
            if appending:  # e.g. a stopped recording run again
                from deltar.cli.errors import warn

                warn(f"{out} already holds a recording: --simulate plays {simulate} from its "
                     "first frame again, so the appended frames repeat the source from its "
                     "start (the camera jumps back); record into a new folder to keep them "
                     "apart")
            rig = SimulatedRig(source, grid=grid, sensor_hz=sensor_hz,
                               max_targets=targets or 1, poses=_source_poses(source),
                               start_time_s=_append_start_s(out, bag))
        else:
            calibration = load_calibration(calib)
            if calibration is None:
                raise ValueError("hardware recording needs --calib for the camera intrinsics")
            intrinsics = calibration.intrinsics
            openers = {"vl53l5cx-ctypes": open_vl53l5cx_ctypes, "sparkfun": open_sparkfun}
            if sensor not in openers:
                raise ValueError(f"--sensor must be one of {sorted(openers)}, got {sensor!r}")
            rig = HardwareRig(OpenCVCamera(camera, (intrinsics.height, intrinsics.width)),
                              openers[sensor](grid=grid, targets_per_zone=targets))
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
        fail(err)
    poses = f", {summary.poses} camera poses" if summary.poses else ""
    typer.echo(f"recorded {summary.images} images, {summary.zone_frames} zone frames, "
               f"{summary.depth_maps} depth maps{poses} over {summary.duration_s:.2f} s "
               f"{'appended to the recording' if appending else 'into'} {out}")


@model_options
@bag_topic_options
def replay_command(
    recording: Path | None = typer.Argument(None, help="Recording folder (or give --bag)."),
    out: Path | None = typer.Option(None, "--out", help="Output folder (outside the "
                                    "recording)."),
    show: bool = typer.Option(False, help="Show depth live in an OpenCV window instead."),
    calib: Path | None = CalibOption,
    model: ModelOptions = MODEL_OPTIONS,
    outputs: str = typer.Option(DEFAULT_OUTPUTS, help="Comma list of output kinds."),
    tolerance: float = typer.Option(0.02, min=0.0, help="Largest image-zone time offset, "
                                    "seconds."),
    time_offset: float | None = typer.Option(None, "--time-offset", help="Camera clock minus "
                                             "sensor clock, seconds, applied when pairing "
                                             "(default: the --calib file's, else 0)."),
    every: int = typer.Option(1, min=1, help="Use every N-th frame."),
    limit: int | None = typer.Option(None, min=1, help="Stop after this many frames."),
    overwrite: bool = typer.Option(False, help="Replace existing outputs."),
    skip_existing: bool = typer.Option(False, "--skip-existing", help="Resume: keep the "
                                       "outputs that exist, write only the missing ones."),
    keep_going: bool = typer.Option(False, "--keep-going", help="Report a frame that "
                                    "fails (unreadable image, refused reading) and go on; "
                                    "the summary counts the failures (exit code 1 if any)."),
    allow_no_zones: bool = AllowNoZonesOption,
    bag: Path | None = BagOption,
    out_bag: Path | None = OutBagOption,
    bag_storage: str = BagStorageOption,
    topics: BagTopics = BAG_TOPICS,
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
    from deltar.cli.robotics import (
        ReplayViewer,
        check_viewer,
        open_viewer,
        replay_bag_command,
    )

    if (recording is None) == (bag is None):
        raise typer.BadParameter("give a RECORDING folder or --bag BAG")
    check_viewer(rerun, rerun_save)  # before the model
    if time_offset is not None and not math.isfinite(time_offset):
        raise typer.BadParameter(f"must be finite, got {time_offset}", param_hint="--time-offset")
    if bag is not None:
        # --out-bag is never replaced (it must not exist), so --overwrite has nothing to do.
        refuse_unused_options({"--keep-going": keep_going, "--skip-existing": skip_existing,
                               "--overwrite": overwrite,
                               "--outputs": outputs != DEFAULT_OUTPUTS},
                              "for replays into an --out folder",
                              "with --bag the output is a new bag, written whole")
        model.check()
        try:
            typer.echo(replay_bag_command(
                bag, model.load,
                load_calibration(calib), out=out, show=show, out_bag=out_bag,
                storage=bag_storage, topics=topics, points=points,
                prefix=topic_prefix, rerun=rerun, rerun_save=rerun_save,
                tolerance=tolerance, every=every, limit=limit, time_offset=time_offset,
                skip_no_zones=not allow_no_zones))
        except (ValueError, FileNotFoundError, FileExistsError, ImportError) as err:
            fail(err)
        return
    viewing = rerun or rerun_save is not None
    if out is not None and show:
        raise typer.BadParameter("give --out DIR or --show, not both (--rerun / --rerun-save "
                                 "go with either)", param_hint="--show")
    if out is None and not show and not viewing:
        raise typer.BadParameter("give --out DIR, or --show (and/or --rerun, --rerun-save)")
    kinds = parse_outputs(outputs)
    if skip_existing and (overwrite or out is None):
        raise typer.BadParameter("--skip-existing resumes writing to --out: give it without "
                                 "--overwrite", param_hint="--skip-existing")
    model.check()
    calibration = load_calibration(calib)
    from deltar.calibration.rig import pairing_time_offset

    time_offset = pairing_time_offset(calibration, time_offset)
    total = _check_replay(recording, out, kinds, (tolerance, time_offset), every, limit,
                          overwrite, show, skip_existing, skip_no_zones=not allow_no_zones)
    _check_calibration_fits(calibration, calib, recording)
    estimator = model.load()
    if estimator.onnx_model is not None:  # its zone grid is fixed: checked before any frame
        from deltar.io.recording import Recording

        estimator.onnx_model.check_grid(Recording(recording).meta.grid,
                                        f"the recording {recording}")
    viewer = ReplayViewer(open_viewer(rerun, rerun_save), recording, calibration)
    failed: list[tuple[str, Exception]] = []

    def failure(pair, err: Exception) -> None:
        failed.append((pair.color_path.name, err))
        warn(f"skipped {pair.color_path.name}: {format_error(err)}")

    on_failure = failure if keep_going else None
    if out is None:
        items = map(viewer, replay(recording, estimator, calibration=calibration,
                                   tolerance_s=tolerance, time_offset_s=time_offset,
                                   every=every, limit=limit,
                                   skip_no_zones=not allow_no_zones, on_failure=on_failure))
        if show:
            _show_live(items)
        else:
            for _ in items:
                pass
        viewer.close()
        _fail_if_any(failed, total)
        return
    with ProgressReport("replaying", total=total) as progress:

        def each(item) -> None:
            viewer(item)
            progress.advance()

        written = replay_to_folder(recording, estimator, out, kinds=kinds,
                                   calibration=calibration, tolerance_s=tolerance,
                                   time_offset_s=time_offset, every=every, limit=limit,
                                   overwrite=overwrite, on_item=each,
                                   skip_no_zones=not allow_no_zones,
                                   skip_existing=skip_existing,
                                   on_failure=None if on_failure is None else
                                   lambda pair, err: (on_failure(pair, err),
                                                      progress.advance()))
    viewer.close()
    typer.echo(f"wrote {len(written)} files to {out}")
    _fail_if_any(failed, total)


def _fail_if_any(failed: list[tuple[str, Exception]], total: int) -> None:
    """End a ``--keep-going`` replay with exit code 1 when frames failed."""
    if failed:
        name, err = failed[0]
        fail(f"{len(failed)} of {total} frames failed (first: {name}: {format_error(err)})")


def _check_replay(recording: Path, out: Path | None, kinds, pairing: tuple[float, float],
                  every: int, limit: int | None, overwrite: bool, show: bool,
                  skip_existing: bool = False, skip_no_zones: bool = True) -> int:
    """Check a replay's recording and outputs before the model; return how many frames
    it will predict (with ``skip_existing``, those still missing an output), chosen as
    :func:`~deltar.capture.replay.replay` chooses them (one pair per colour image,
    :func:`~deltar.capture.replay.replay_pairs`; every ``every``-th pair, those
    without a valid zone left out when ``skip_no_zones``, at most ``limit``).

    ``pairing`` is (tolerance, time offset) in seconds.
    """
    import warnings

    from deltar.capture.replay import replay_pairs
    from deltar.cli.checks import display, existing_outputs, output_folder
    from deltar.inference.outputs import OUTPUT_KINDS
    from deltar.io.input_file import refuse_input_as_output
    from deltar.io.recording import Recording

    if show:
        display("--show")
    rec = Recording(recording)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # replaying warns about skipped frames itself
        pairs = replay_pairs(rec, rec.pairs(tolerance_s=pairing[0],
                                            time_offset_s=pairing[1]), pairing[1])
    if not pairs:
        frames = len(rec.zone_frames())
        raise ValueError(f"{recording}: nothing to replay: " + (
            f"none of its {frames} zone frame(s) has a colour image within --tolerance "
            f"{pairing[0]:g} s" if frames else f"{rec.zones_path.name} holds no zone frame"))
    selected = [p for p in pairs[::every]
                if not (skip_no_zones and p.zone_frame.valid_count == 0)][:limit]
    if out is not None:
        refuse_input_as_output(out, [recording], "--out", folder=True)
        output_folder(out, "--out")
        def outputs(pair):
            return [out / f"{pair.color_path.stem}{OUTPUT_KINDS[k]}" for k in kinds]

        if skip_existing:
            return sum(1 for p in selected if not all(o.exists() for o in outputs(p)))
        if not overwrite:
            existing_outputs((o for p in selected for o in outputs(p)), resumable=True)
    return len(selected)


def _check_calibration_fits(calibration, calib: Path | None, recording: Path) -> None:
    """``--calib`` against the recording's image size and zone grid, before the model;
    without it, a warning unless the recording is simulated (its sensor sits on the
    camera's axis, as the placement without a calibration assumes)."""
    from deltar.io.recording import Recording

    meta = Recording(recording).meta
    if calibration is None:
        if meta.sensor_model != "simulated":
            from deltar.cli.errors import warn

            warn(f"no --calib: the zones are placed with {recording}'s camera (meta.json) and "
                 "the sensor on its optical axis; give your rig's calibration with --calib "
                 "(docs/calibration.md)")
        return
    check_calibration_fits(calibration, calib, meta, recording)


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


def _source_poses(source) -> list | None:
    """The per-frame camera poses of an RGB-D folder source (pose files beside its
    frames, ``RGBDReader.poses``), or None (other sources, or a folder without any)."""
    from deltar.data.rgbd import RGBDReader

    return source.poses() if isinstance(source, RGBDReader) else None


def _append_start_s(out: Path, bag: bool) -> float:
    """Seconds at which a simulated rig's clock starts: after the end of the recording
    already in ``out`` (it appends; its files are named by time), else 0."""
    from deltar.capture.drivers import SIMULATED_CAMERA_HZ
    from deltar.io.recording import META_FILE, Recording

    if bag or not (out / META_FILE).is_file():
        return 0.0
    end = Recording(out).end_time_s()
    return 0.0 if end is None else end + 1.0 / SIMULATED_CAMERA_HZ
