"""``deltar predict``: depth for one image or a folder of images and zone frames."""

from __future__ import annotations

from pathlib import Path

import typer

from deltar.cli.frame_options import (
    AllowNoZonesOption,
    load_calibration,
    parse_outputs,
)
from deltar.cli.model_options import MODEL_OPTIONS, ModelOptions, model_options
from deltar.cli.robotics import (
    RerunOption,
    RerunSaveOption,
)
from deltar.io.file_pairs import pair_by_stem
from deltar.io.input_file import refuse_input_as_output

_DEFAULT_OUTPUTS = "png16,npy,sigma,color,ply,panel"
#: The option that lets frames without a valid zone through, named in the refusal.
_ALLOW = "--allow-no-zones"


@model_options
def predict_command(
    image: Path | None = typer.Option(None, "--image", help="One RGB image."),
    zones: Path | None = typer.Option(None, "--zones", help="Its zone frame (.json/.npz, or "
                                      "a raw driver dump .json)."),
    images: Path | None = typer.Option(None, "--images", help="Folder of images (folder "
                                       "mode, paired with --zones-dir by file stem)."),
    zones_dir: Path | None = typer.Option(None, "--zones-dir", help="Folder of zone frames."),
    driver_orientation: str = typer.Option(
        "none", "--driver-orientation", help="Raw driver dumps only: how the driver's zone "
        "grid maps onto the image, a comma list of flip_ud, flip_lr, rot90:K or none "
        "(e.g. flip_ud for vl53l5cx-ctypes, docs/formats.md)."),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    calib: Path | None = typer.Option(
        None, "--calib", help="Rig calibration JSON (deltar calibrate); without it the zones "
        "are placed by a nominal geometry (the ZJU-L5 rig's camera scaled to the image)."),
    model: ModelOptions = MODEL_OPTIONS,
    outputs: str = typer.Option(_DEFAULT_OUTPUTS, help="Comma list of png16 (uint16 mm), "
                                "npy (float32 m), sigma (the uncertainty, float32 m), color, "
                                "ply (point cloud), panel."),
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
    from deltar.cli.checks import existing_outputs, output_folder
    from deltar.cli.errors import fail, format_error, warn
    from deltar.cli.progress import ProgressReport
    from deltar.cli.robotics import open_viewer
    from deltar.inference.folder import check_valid_zones, plan_jobs, run_jobs

    single = image is not None or zones is not None
    folder = images is not None or zones_dir is not None
    if single == folder or (single and (image is None or zones is None)) or \
            (folder and (images is None or zones_dir is None)):
        raise typer.BadParameter("give --image and --zones, or --images and --zones-dir")
    if overwrite and skip_existing:
        raise typer.BadParameter("give --overwrite or --skip-existing, not both")
    kinds = parse_outputs(outputs)
    from deltar.cli.robotics import check_viewer, parse_orientation

    check_viewer(rerun, rerun_save)  # before the model

    orientation = parse_orientation(driver_orientation, "--driver-orientation")
    model.check()
    first = None
    if single:
        from deltar.data.rgbd_files import read_color
        from deltar.io.zone_file import load_zone_frame

        pairs, unpaired = [(image, zones)], []
        first = (read_color(image), load_zone_frame(zones, orientation=orientation))
        check_valid_zones(first[1], zones, allow_no_zones, _ALLOW)
    else:
        pairs, unpaired = pair_by_stem(images, zones_dir)
        if not pairs:
            raise ValueError(f"no image in {images} has a zone file with the same stem in "
                             f"{zones_dir}")
        # Outputs in an input folder would replace its other files and become frames of
        # the next run.
        refuse_input_as_output(out, [images, zones_dir], "--out", folder=True)
    output_folder(out, "--out")
    jobs, complete, existing = plan_jobs(pairs, out, kinds, overwrite=overwrite,
                                         skip_existing=skip_existing)
    existing_outputs(existing, resumable=True)
    calibration = load_calibration(calib)
    if first is not None:
        from deltar.camera import check_image

        check_image(first[0], str(image))
        if calibration is not None and calibration.grid != first[1].grid:
            raise ValueError(f"{zones} has a {first[1].grid}x{first[1].grid} zone grid but "
                             f"--calib {calib} is for {calibration.grid}x{calibration.grid}")
        if calibration is not None:
            calibration.check_image_size(first[0].shape[:2], str(image), f"--calib {calib}")
    elif calibration is not None and not keep_going:  # with it, such frames fail alone
        _check_image_sizes(jobs, calibration, f"--calib {calib}")
    if unpaired:
        warn(f"{len(unpaired)} file{'s' if len(unpaired) > 1 else ''} without a partner "
             f"{'are' if len(unpaired) > 1 else 'is'} left out: "
             f"{unpaired[:5]}{' ...' if len(unpaired) > 5 else ''}")
    if complete:
        typer.echo(f"{complete} frame(s) already have every output (--skip-existing)")
    if not jobs:
        typer.echo(f"nothing to do: every output exists in {out}")
        return
    estimator = model.load()
    if calibration is None:
        warn("no --calib: the zones are placed by the nominal geometry (the ZJU-L5 rig's "
             "camera scaled to the image, the sensor on its axis); give your rig's "
             "calibration with --calib (docs/calibration.md)")
    viewer = open_viewer(rerun, rerun_save)

    def on_prediction(job, rgb, prediction) -> None:
        if viewer is not None:
            viewer.log_prediction(rgb, prediction, calibration=calibration,
                                  fov_deg=estimator.fov_deg)
        if prediction.image_only:
            warn(f"{job.image.name}: no valid zone: wrote an image-only estimate "
                 "(metric scale unknown, uncertainty at least the depth; flagged in the PNG "
                 "and PLY metadata and the panel)")

    with ProgressReport("predicting", total=len(jobs),
                        terminal=None if len(jobs) > 1 else False) as progress:
        summary = run_jobs(
            jobs, estimator, out, calibration=calibration, overwrite=overwrite,
            keep_going=keep_going, allow_no_zones=allow_no_zones, allow_option=_ALLOW,
            orientation=orientation,
            first=first if first is not None and jobs else None,
            on_prediction=on_prediction,
            on_failure=lambda name, err: warn(f"skipped {name}: {format_error(err)}"),
            on_frame=progress.advance if len(jobs) > 1 else None)
    if viewer is not None:
        viewer.close()
    image_only = len(summary.image_only)
    typer.echo(f"wrote {summary.written} prediction(s) to {out}"
               + (f" ({image_only} image-only)" if image_only else ""))
    if summary.failed:
        name, err = summary.failed[0]
        fail(f"{len(summary.failed)} of {len(jobs)} frames failed (first: {name}: "
             f"{format_error(err)}); re-run with --skip-existing after fixing them")


def _check_image_sizes(jobs, calibration, name: str) -> None:
    """Refuse, before the model, a folder's images of another size than the calibrated
    resolution (read from their headers). An unreadable image is left to its frame (it
    fails there, or is skipped with ``--keep-going``)."""
    from deltar.data.rgbd_files import color_image_size

    for job in jobs:
        try:
            size = color_image_size(job.image)
        except (OSError, ValueError):
            continue
        calibration.check_image_size(size, str(job.image), name)
