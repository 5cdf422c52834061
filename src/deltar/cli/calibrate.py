"""``deltar calibrate``: ToF sensor to camera calibration of a recording."""

from __future__ import annotations

from pathlib import Path

import typer


def _floats(text: str, count: int, name: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"{name} must be {count} comma-separated numbers") from None
    if len(values) != count:
        raise typer.BadParameter(f"{name} must be {count} comma-separated numbers, got {text!r}")
    return values


def calibrate_command(
    recording: Path = typer.Argument(..., help="Recording folder (meta.json, zones.jsonl, "
                                     "color/, depth/)."),
    out: Path = typer.Option(..., "--out", help="Calibration JSON to write."),
    tolerance_s: float = typer.Option(0.02, min=0.0, help="Max time gap between a zone "
                                      "frame and its images, seconds."),
    fov: str = typer.Option("", help="Sensor field of view 'H,V' in degrees (default: the "
                            "recording's)."),
    nominal_roll_deg: float = typer.Option(90.0, help="Nominal roll of the sensor about the "
                                           "camera's viewing direction, degrees."),
    nominal_translation: str = typer.Option("0,0,0", help="Nominal sensor position in the "
                                            "camera frame 'x,y,z', metres."),
    slam_cloud: Path | None = typer.Option(None, help="SLAM map (PLY) instead of depth images."),
    slam_trajectory: Path | None = typer.Option(None, help="Camera trajectory of the SLAM map "
                                                "(TUM format)."),
    target: str = typer.Option("", "--target", help="A printed board instead of depth "
                               "images: charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT] (squares) "
                               "or checkerboard:COLSxROWS:SQUARE_M (inner corners), metres."),
    calibrate_intrinsics: bool = typer.Option(False, "--calibrate-intrinsics", help="With "
                                              "--target: also estimate the camera "
                                              "intrinsics and lens distortion from the "
                                              "board views (record about a third of them "
                                              "close enough that the board fills most of "
                                              "the image)."),
    time_offset: str = typer.Option("0", "--time-offset", help="Camera clock minus sensor "
                                    "clock, seconds, or 'auto' (with --target: estimated "
                                    "from the board's distance over time)."),
    plot: Path | None = typer.Option(None, help="Folder for before/after zone pictures."),
    overwrite: bool = typer.Option(False, help="Replace an existing --out file."),
) -> None:
    """Calibrate the ToF sensor against the camera from frames facing planes.

    The camera's side comes from depth images, a SLAM map, or (--target) a printed
    board fixed on a flat surface. Every option and output is checked before the (long)
    calibration; if the nominal roll guess leaves no consistent set of frames, the other
    quarter turns are tried and the one that works is suggested.
    """
    import warnings

    import numpy as np

    from deltar.calibration.extrinsic import nominal_extrinsics
    from deltar.calibration.pipeline import calibrate_recording
    from deltar.calibration.rig import MAX_TRANSLATION_M
    from deltar.calibration.slam import read_ply_points, read_tum_trajectory
    from deltar.cli.checks import finite, output_file, output_folder
    from deltar.io.input_file import refuse_input_as_output
    from deltar.io.recording import Recording

    if (slam_cloud is None) != (slam_trajectory is None):
        raise typer.BadParameter("give --slam-cloud and --slam-trajectory together")
    spec = board_spec_option(target) if target else None
    if spec is not None and slam_cloud is not None:
        raise typer.BadParameter("--target calibrates from board images: leave out "
                                 "--slam-cloud / --slam-trajectory")
    if calibrate_intrinsics and spec is None:
        raise typer.BadParameter("--calibrate-intrinsics needs --target (the board views)")
    offset = time_offset_option(time_offset, allow_auto=spec is not None)
    inputs = (recording, slam_cloud, slam_trajectory)
    refuse_input_as_output(out, inputs, "--out")
    if out.exists() and not overwrite:
        raise typer.BadParameter(f"{out} exists; pass --overwrite to replace it")
    output_file(out, "--out", overwrite)
    fov_deg = _floats(fov, 2, "--fov") if fov else None
    if fov_deg is not None and not all(np.isfinite(v) and 0 < v < 180 for v in fov_deg):
        raise typer.BadParameter(f"angles must be in (0, 180) degrees, got {fov!r}",
                                 param_hint="--fov")
    finite(nominal_roll_deg, "--nominal-roll-deg")
    finite(tolerance_s, "--tolerance-s")
    translation = _floats(nominal_translation, 3, "--nominal-translation")
    if not all(np.isfinite(translation)):
        raise typer.BadParameter(f"must be finite, got {nominal_translation!r}",
                                 param_hint="--nominal-translation")
    if np.linalg.norm(translation) >= MAX_TRANSLATION_M:
        raise typer.BadParameter(f"the sensor is {np.linalg.norm(translation):g} m from the "
                                 f"camera, got {nominal_translation!r}; a rig's sensor sits "
                                 f"within {MAX_TRANSLATION_M:g} m of it (metres, not "
                                 "millimetres)", param_hint="--nominal-translation")
    if plot is not None:
        refuse_input_as_output(plot, inputs, "--plot", folder=True)
        if plot.resolve() == out.resolve():  # found only after calibrating, otherwise
            raise typer.BadParameter(f"{plot} is also --out: the pictures go in a folder "
                                     "of their own", param_hint="--plot")
        output_folder(plot, "--plot")
        if not overwrite and plot.is_dir() and any(plot.glob("zones_*.png")):
            raise FileExistsError(f"--plot {plot} already holds zone pictures; pass "
                                  "--overwrite to replace them")
        from deltar.extras import require_extra

        require_extra("matplotlib", "--plot (zone pictures)")  # before calibrating
    nominal = nominal_extrinsics(nominal_roll_deg, translation)
    rec = Recording(recording)
    board = None
    if spec is not None:
        from deltar.calibration.board_pipeline import calibrate_recording_with_board

        result, board = calibrate_recording_with_board(
            rec, spec, nominal, tolerance_s=tolerance_s, time_offset_s=offset,
            fov_deg=fov_deg, calibrate_intrinsics=calibrate_intrinsics)
        _report(result, nominal, out, overwrite, tolerance_s, board)
        _plots(plot, rec, result, nominal, tolerance_s, overwrite)
        return
    trajectory = points = None
    if slam_cloud is not None:
        points = read_ply_points(slam_cloud)
        trajectory = read_tum_trajectory(slam_trajectory)

    def run(guess):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # skipped frames are reported below
            return calibrate_recording(rec, guess, tolerance_s=tolerance_s, fov_deg=fov_deg,
                                       trajectory=trajectory, slam_points_world=points,
                                       time_offset_s=offset)

    try:
        result = run(nominal)
    except ValueError as err:
        raise ValueError(f"{err}{_roll_hint(run, nominal_roll_deg, translation)}") from None
    _report(result, nominal, out, overwrite, tolerance_s)
    _plots(plot, rec, result, nominal, tolerance_s, overwrite)


def board_spec_option(text: str, option: str = "--target"):
    """The ``BoardSpec`` of an option's text (usage error naming the option if malformed)."""
    from deltar.calibration.board import parse_board_spec

    try:
        return parse_board_spec(text, option)
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint=option) from None


def time_offset_option(text: str, allow_auto: bool) -> float | str:
    """``--time-offset``: seconds, or ``"auto"`` where the command can estimate it."""
    import math

    if text.strip().lower() == "auto":
        if not allow_auto:
            raise typer.BadParameter("'auto' needs --target (the offset is estimated from "
                                     "the board's distance); give SECONDS",
                                     param_hint="--time-offset")
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise typer.BadParameter(f"must be seconds or 'auto', got {text!r}",
                                 param_hint="--time-offset") from None
    if not math.isfinite(value):
        raise typer.BadParameter(f"must be finite, got {text!r}", param_hint="--time-offset")
    return value


def _report(result, nominal, out: Path, overwrite: bool, tolerance_s: float,
            board=None) -> None:
    """Save the calibration and print the report (the same for every path)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    calib = result.calibration
    calib.save(out, overwrite=overwrite)
    used, skipped = len(result.observations), len(result.skipped)
    if board is not None:
        typer.echo(f"board found in {board.views_with_board} of {board.images_searched} "
                   f"paired images (median pose reprojection {board.pose_rms_px:.2f} px)")
        if board.time_offset is not None:
            est = board.time_offset
            typer.echo(f"time offset (camera - sensor): {est.offset_s * 1000:+.1f} ms, "
                       f"estimated from {est.samples} zone frames (distance misfit "
                       f"{100 * est.residual_m:.2f} cm, {100 * est.residual_at_zero_m:.2f} cm "
                       "with no offset)")
        elif board.time_offset_s:
            typer.echo(f"time offset (camera - sensor): {board.time_offset_s * 1000:+.1f} ms")
        if board.intrinsics_rms_px is not None:
            k = calib.intrinsics
            typer.echo(f"intrinsics: fx {k.fx:.2f}, fy {k.fy:.2f}, cx {k.cx:.2f}, cy "
                       f"{k.cy:.2f} px; distortion " + ", ".join(f"{v:+.4f}" for v in
                                                                calib.distortion)
                       + f" (reprojection RMS {board.intrinsics_rms_px:.2f} px)")
            if board.camera is not None:
                sd = board.camera.sd
                typer.echo(f"intrinsics sd: fx {sd[0]:.2f}, fy {sd[1]:.2f}, cx {sd[2]:.2f}, "
                           f"cy {sd[3]:.2f} px (the principal point turns the board "
                           f"planes by {board.camera.principal_point_sd_deg:.2f} deg, 1 sd)")
    typer.echo(f"frames used: {used}, skipped: {skipped}"
               + (f", zone frames without an image within {tolerance_s} s: {result.unpaired}"
                  if result.unpaired else ""))
    for name, reason in result.skipped[:5]:
        typer.echo(f"  skipped {name}: {reason}")
    delta = Rotation.from_matrix(calib.extrinsics.rotation @ nominal.rotation.T)
    angle = np.degrees(Rotation.from_matrix(calib.extrinsics.rotation).magnitude())
    typer.echo(f"rotation: {angle:.2f} deg total, {np.degrees(delta.magnitude()):.2f} deg "
               "from the nominal guess")
    typer.echo("translation (m): " + ", ".join(f"{v:+.4f}" for v in
                                                calib.extrinsics.translation_m))
    typer.echo(f"mean zone-to-cloud distance: {100 * result.distance_before_m:.2f} cm before, "
               f"{100 * result.distance_after_m:.2f} cm after")
    expected = getattr(board, "uncertainty", None)
    if expected is not None:
        typer.echo(f"expected error from the zones' noise ({100 * expected.zone_noise_m:.1f} cm, "
                   f"1 sd): rotation {expected.rotation_rms_deg:.2f} deg, translation "
                   f"{1000 * expected.translation_rms_m:.1f} mm")
    scale_m = calib.residuals.get("board_scale_translation_m", 0.0)
    if scale_m > 0:
        typer.echo(f"plus about {1000 * scale_m:.0f} mm of translation from the board's "
                   "printed size (the warning above): not counted in the expected error")
    typer.echo(f"wrote {out}; check it on another recording with deltar check-calibration, "
               "then give it to predict / replay / map with --calib")


def _plots(plot: Path | None, rec, result, nominal, tolerance_s: float,
           overwrite: bool) -> None:
    """Before/after zone pictures of three frames (``--plot``)."""
    import warnings

    import numpy as np

    from deltar.calibration.rig import RigCalibration

    if plot is not None:
        from deltar.calibration.plot import plot_zones_before_after

        calib = result.calibration
        nominal_calib = RigCalibration(calib.intrinsics, nominal, calib.grid, calib.fov_deg,
                                       calib.sensor_model, distortion=calib.distortion)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pairs = rec.pairs(tolerance_s, time_offset_s=calib.time_offset_s)
        except FileNotFoundError as err:
            typer.echo(f"no pictures drawn: {err}")
            pairs = []
        picks = sorted({round(i) for i in np.linspace(0, len(pairs) - 1, min(3, len(pairs)))}
                       ) if pairs else []
        for index in picks:
            pair = pairs[index]
            ns = round(pair.zone_frame.timestamp_s * 1e9)
            path = plot_zones_before_after(
                plot / f"zones_{ns}.png", calib.undistort_image(pair.load_color()),
                pair.zone_frame, nominal_calib,
                calib, title=f"t = {pair.zone_frame.timestamp_s:.3f} s", overwrite=overwrite)
            typer.echo(f"wrote {path}")


def _roll_hint(run, roll_deg: float, translation) -> str:
    """After a failed calibration: which other quarter-turn roll guess works, if any."""
    from deltar.calibration.extrinsic import nominal_extrinsics
    from deltar.calibration.pipeline import other_roll_guesses

    working = []
    for roll in other_roll_guesses(roll_deg):
        try:
            result = run(nominal_extrinsics(roll, translation))
        except ValueError:
            continue
        working.append((len(result.observations), -result.distance_after_m, roll, result))
    if not working:
        return ""
    frames, _, roll, result = max(working)
    return (f". The nominal roll guess --nominal-roll-deg {roll_deg:g} may be wrong: with "
            f"--nominal-roll-deg {roll:g} this recording calibrates ({frames} frames, mean "
            f"zone-to-cloud distance {100 * result.distance_after_m:.2f} cm)")
