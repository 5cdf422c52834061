"""``deltar calibration-board`` (a printable board) and ``deltar check-calibration``."""

from __future__ import annotations

from pathlib import Path

import typer

from deltar.cli.calibrate import board_spec_option, time_offset_option


def calibration_board_command(
    target: str = typer.Option(..., "--target", help="charuco:COLSxROWS:SQUARE_M:MARKER_M"
                               "[:DICT] or checkerboard:COLSxROWS:SQUARE_M (metres)."),
    out: Path = typer.Option(..., "--out", help="Page to write: .pdf or .png."),
    paper: str = typer.Option("a4", help="Paper: a4 or letter."),
    dpi: int = typer.Option(300, min=72, max=1200, help="PNG resolution, dots per inch."),
    overwrite: bool = typer.Option(False, help="Replace an existing --out file."),
) -> None:
    """Write a calibration board at true scale on one page, its spec in the margin."""
    from deltar.calibration.board_print import write_board_page
    from deltar.cli.checks import output_file

    spec = board_spec_option(target)
    if paper.lower() not in ("a4", "letter"):
        raise typer.BadParameter(f"must be a4 or letter, got {paper!r}", param_hint="--paper")
    if out.suffix.lower() not in (".pdf", ".png"):
        raise typer.BadParameter(f"must end in .pdf or .png, got {out.name!r}",
                                 param_hint="--out")
    output_file(out, "--out", overwrite)
    path = write_board_page(out, spec, paper=paper.lower(), dpi=dpi, overwrite=overwrite)
    width, height = (1000 * v for v in spec.size_m)
    typer.echo(f"wrote {path}: {spec.text()}, {width:.0f} x {height:.0f} mm on {paper.upper()}; "
               "print at 100 % and measure a square before calibrating")


#: Exit status of ``check-calibration`` when the calibration does not fit the recording.
CALIBRATION_DOES_NOT_FIT = 3


def check_calibration_command(
    recording: Path = typer.Argument(..., help="Recording folder (meta.json, zones.jsonl, "
                                     "color/, and depth/ unless --target)."),
    calib: Path = typer.Option(..., "--calib", help="Rig calibration JSON to score."),
    target: str = typer.Option("", "--target", help="The board the recording shows (score "
                               "against its plane); default: the depth images."),
    plot: Path | None = typer.Option(None, help="PNG picture of the residuals."),
    tolerance_s: float = typer.Option(0.02, min=0.0, help="Max time gap between a zone "
                                      "frame and its image, seconds."),
    time_offset: str = typer.Option("", "--time-offset", help="Camera clock minus sensor "
                                    "clock, seconds (default: the calibration's)."),
    overwrite: bool = typer.Option(False, help="Replace an existing --plot file."),
) -> None:
    """Score a calibration on a recording: per-zone residuals against the board or depth.

    The last line says whether the rig still fits; the exit status says it to scripts:
    0 when it fits, 3 when it does not (1 and 2 are bad input, as everywhere).
    """
    import numpy as np

    from deltar.calibration.check import (
        FIT_BIAS_M,
        FIT_MEDIAN_ABS_M,
        FIT_TILT_DEG,
        check_calibration,
        plot_check,
    )
    from deltar.calibration.rig import RigCalibration
    from deltar.cli.checks import finite, output_file
    from deltar.io.recording import Recording

    finite(tolerance_s, "--tolerance-s")  # inf would pair frames any time apart
    spec = board_spec_option(target) if target else None
    offset = time_offset_option(time_offset, allow_auto=False) if time_offset else None
    if plot is not None:
        from deltar.io.input_file import refuse_input_as_output

        if plot.suffix.lower() != ".png":
            raise typer.BadParameter(f"{plot} is not a .png file: the plot is a PNG picture",
                                     param_hint="--plot")
        refuse_input_as_output(plot, [recording, calib], "--plot")
        output_file(plot, "--plot", overwrite)
        from deltar.extras import require_extra

        require_extra("matplotlib", "--plot (residual picture)")  # before scoring
    calibration = RigCalibration.load(calib)
    rec = Recording(recording)
    check = check_calibration(rec, calibration, spec=spec, tolerance_s=tolerance_s,
                              time_offset_s=offset, calibration_name=f"--calib {calib}")
    typer.echo(f"frames scored: {len(check.frame_names)} against the {check.reference}"
               + (f" ({check.skipped} without one)" if check.skipped else ""))
    typer.echo(f"zone residuals: median |r| {100 * check.median_abs_m:.2f} cm, bias "
               f"{100 * check.bias_m:+.2f} cm, RMS {100 * check.rms_m:.2f} cm; "
               f"{100 * check.off_surface_fraction:.0f} % of zones off the surface; tilt "
               f"across the zones {check.tilt_rms_deg:.1f} deg rms")
    worst = check.zone_median_m()
    if np.isfinite(worst).any():
        r, c = np.unravel_index(np.nanargmax(np.abs(worst)), worst.shape)
        typer.echo(f"largest zone median: {100 * worst[r, c]:+.2f} cm at row {r}, column {c}")
    if plot is not None:
        typer.echo(f"wrote {plot_check(plot, check, overwrite=overwrite)}")
    if check.fits:
        typer.echo(f"the calibration fits this recording (median |r| <= "
                   f"{100 * FIT_MEDIAN_ABS_M:g} cm, |bias| <= {100 * FIT_BIAS_M:g} cm, tilt <= "
                   f"{FIT_TILT_DEG:g} deg)")
    else:
        typer.echo("the calibration does NOT fit this recording (median |r| > "
                   f"{100 * FIT_MEDIAN_ABS_M:g} cm, |bias| > {100 * FIT_BIAS_M:g} cm or tilt > "
                   f"{FIT_TILT_DEG:g} deg): the rig "
                   "has moved or the calibration is for another rig; recalibrate (or, for a "
                   "moving camera, check the clocks' offset: --time-offset)")
        raise typer.Exit(CALIBRATION_DOES_NOT_FIT)
