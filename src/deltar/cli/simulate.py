"""``deltar simulate``: turn an RGB-D source into a ZJU-L5-layout set with simulated zones."""

from __future__ import annotations

from pathlib import Path

import typer

#: Bytes a simulated frame takes per pixel at most (uint8 RGB + float32 depth, before
#: compression); zones and metadata are a few KiB more.
SET_BYTES_PER_PIXEL = 7


def _parse_intrinsics(text: str | None, height: int, width: int):
    from deltar.camera import CameraIntrinsics

    if text is None:
        return None
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError as err:
        raise typer.BadParameter(f"--intrinsics must be 'fx,fy,cx,cy', got {text!r}") from err
    return CameraIntrinsics(fx, fy, cx, cy, width, height)


def _cnh_config(enabled: bool, bins: int | None, span: str | None):
    """The CNH bin configuration asked for, or None (no histograms)."""
    from deltar.sensor.cnh import CNHConfig

    if not (enabled or bins is not None or span is not None):
        return None
    if bins is None and span is None:
        return CNHConfig()
    near, far = CNHConfig().range_m
    if span is not None:
        try:
            near, far = (float(v) for v in span.split(":"))
        except ValueError as err:
            raise typer.BadParameter(f"--cnh-range must look like '0.2:4.0', got {span!r}",
                                     param_hint="--cnh-range") from err
    try:
        return CNHConfig.from_range(near, far, bins or CNHConfig().num_bins)
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="--cnh-range") from err


def simulate_command(
    src: str = typer.Argument(..., help="RGB-D folder, NYU .mat / split .json, or "
                              "'procedural:<frames>[:<seed>[:<H>x<W>]]'."),
    out: Path = typer.Argument(..., help="Output folder (must not exist or be empty)."),
    grid: int = typer.Option(8, help="Zones per side (4 or 8)."),
    layout: str = typer.Option("calibrated", help="Zone placement: 'calibrated' (45x45 deg "
                               "FoV projected with the camera intrinsics) or 'aligned' (the "
                               "release's 56 px grid centred in the image)."),
    start: int = typer.Option(0, help="First frame index."),
    stop: int | None = typer.Option(None, help="Stop before this frame index."),
    step: int = typer.Option(1, help="Take every STEP-th frame."),
    limit: int | None = typer.Option(None, help="Write at most this many frames."),
    depth_scale: float | None = typer.Option(None, help="Raw depth units per metre for "
                                             "folders (default: per layout)."),
    intrinsics: str | None = typer.Option(None, help="Camera intrinsics 'fx,fy,cx,cy' in "
                                          "pixels, overriding the source's."),
    split: str = typer.Option("test", help="Split name written to data.json (and read "
                              "from a NYU split .json)."),
    drop_fraction: float = typer.Option(0.0, min=0.0, max=1.0, help="Degraded signal: make "
                                        "this fraction of each frame's valid zones invalid."),
    bias_prob: float = typer.Option(0.0, min=0.0, max=1.0, help="Degraded signal: "
                                    "probability that a remaining zone's mean is biased."),
    bias_mean: float = typer.Option(0.10, help="Mean of the bias added to those zone "
                                    "means, metres."),
    bias_std: float = typer.Option(0.15, min=0.0, help="Standard deviation of that bias, "
                                   "metres."),
    seed: int = typer.Option(0, help="Seed of the degradation draws (frame i draws from "
                             "(seed, i))."),
    cnh: bool = typer.Option(False, "--cnh", help="Also write per-zone compact normalised "
                             "histograms like ST's VL53L7CH/L8CH (default: 18 bins over "
                             "0-4.73 m, ST's example configuration)."),
    cnh_bins: int | None = typer.Option(None, "--cnh-bins", min=1, max=1024,
                                        help="CNH bins per zone (implies --cnh)."),
    cnh_range: str | None = typer.Option(None, "--cnh-range", help="CNH range 'NEAR:FAR' "
                                         "in metres (implies --cnh)."),
    no_target_flags: bool = typer.Option(True, "--no-target-flags/--without-no-target-flags",
                                         help="Write the zones that reported no target "
                                         "(ST status 255); without: those zones are just "
                                         "invalid, as the released ZJU-L5 files store them."),
    targets: int = typer.Option(1, "--targets", min=1, max=4, help="Targets per zone to "
                                "report, 1-4 (ST's VL53L5CX_NB_TARGET_PER_ZONE): with more "
                                "than 1, a zone that sees surfaces at least 0.6 m apart "
                                "reports each, strongest first."),
) -> None:
    """Simulate L5 zone readings for RGB-D frames and write them as a ZJU-L5 set.

    Zones whose pixels lie mostly beyond the sensor's 4 m range are written as "no
    target" (ST status 255), as the sensor reports them. With --drop-fraction /
    --bias-prob the readings are degraded as a real sensor's can be (zones lost, biased
    means), reproducibly from --seed; the no-target zones stay.
    """
    import warnings

    import numpy as np

    from deltar.cli.checks import finite, output_folder
    from deltar.cli.progress import ProgressReport
    from deltar.data.simulated import simulate_set
    from deltar.data.sources import open_source
    from deltar.extras import require_extra
    from deltar.io.input_file import refuse_input_as_output
    from deltar.io.resources import check_free_space
    from deltar.sensor.augment import SignalAugmentation

    if grid not in (4, 8):
        raise typer.BadParameter(f"--grid must be 4 or 8, got {grid}")
    from deltar.data.simulated import SET_LAYOUTS

    if layout not in SET_LAYOUTS:
        raise typer.BadParameter(f"--layout must be one of {SET_LAYOUTS}, got {layout!r}")
    if step < 1 or start < 0 or (limit is not None and limit < 1) or \
            (stop is not None and stop < 0):
        raise typer.BadParameter("--start and --stop must be >= 0, --step and --limit >= 1")
    if not split.strip():  # the set's data.json would list its frames under ""
        raise typer.BadParameter("must be a non-empty name", param_hint="--split")
    finite(bias_mean, "--bias-mean")
    finite(bias_std, "--bias-std")
    cnh_config = _cnh_config(cnh, cnh_bins, cnh_range)
    # Both draw or bin with PyTorch (the training pipeline's code, so a set is the same
    # whichever install makes it): say so before any work, naming the option.
    if drop_fraction > 0 or bias_prob > 0:
        require_extra("torch", "--drop-fraction / --bias-prob (degraded readings)")
    if cnh_config is not None:
        require_extra("torch", "--cnh / --cnh-bins / --cnh-range (histograms)")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise typer.BadParameter(f"output {out} exists and is not an empty folder; refusing "
                                 "to write into it", param_hint="OUT")
    refuse_input_as_output(out, [None if src.startswith("procedural:") else Path(src)],
                           "OUT", folder=True)
    output_folder(out, "OUT")
    if depth_scale is not None:
        finite(depth_scale, "--depth-scale", positive=True)
    try:
        with warnings.catch_warnings():
            if intrinsics is not None:  # replaced below: no "assuming defaults" warning
                warnings.simplefilter("ignore")
            source = open_source(src, depth_scale=depth_scale, split=split)
        if intrinsics is not None:
            height, width = source[0].depth_m.shape
            try:
                given = _parse_intrinsics(intrinsics, height, width)
            except ValueError as err:
                raise typer.BadParameter(str(err), param_hint="--intrinsics") from err
            source = open_source(src, depth_scale=depth_scale, split=split, intrinsics=given)
    except (OSError, ValueError) as err:
        raise typer.BadParameter(str(err), param_hint="SRC") from err
    # A range is sliced without listing every frame of a long source first.
    indices = list(range(len(source))[start:stop:step][:limit])
    if not indices:
        raise typer.BadParameter(f"no frames selected from {len(source)} (check --start, "
                                 "--stop, --step)")
    height, width = source[indices[0]].depth_m.shape
    check_free_space(out, len(indices) * (SET_BYTES_PER_PIXEL * height * width + 65536),
                     f"OUT {out} ({len(indices)} frames of {height}x{width})")
    degrade = None
    if drop_fraction > 0 or bias_prob > 0:
        degrade = SignalAugmentation(drop_fraction, bias_prob, bias_mean, bias_std)
    scene = Path(src).stem if not src.startswith("procedural:") else "procedural"
    try:
        with ProgressReport("simulating", total=len(indices)) as progress:
            index, valid_counts = simulate_set(
                source, out, indices, grid=grid, layout=layout, degrade=degrade, seed=seed,
                cnh_config=cnh_config, scene=scene, split=split,
                no_target_flags=no_target_flags, max_targets=targets,
                on_frame=progress.advance)
    except KeyboardInterrupt:  # Ctrl+C or SIGTERM (deltar.cli.errors)
        from deltar.cli.errors import fail, stop_name

        fail(f"interrupted by {stop_name()} after {progress.done} of {len(indices)} frames; "
             f"a set is written whole, so the frames written to {out} were removed: run the "
             "command again", 130)
    typer.echo(f"wrote {len(indices)} frames to {index}; valid zones per frame: mean "
               f"{np.mean(valid_counts):.1f} of {grid * grid}")
    empty = int(np.count_nonzero(np.asarray(valid_counts) == 0))
    if empty:
        from deltar.cli.errors import warn

        warn(f"{empty} of {len(indices)} frames have no valid zone (the scene lies beyond the "
             "sensor's range, or returns no signal): depth from them has no metric anchor, "
             "and methods that need zones cannot use them"
             + ("; the set holds no zone reading at all" if empty == len(indices) else ""))
    if cnh_config is not None:
        near, far = cnh_config.range_m
        typer.echo(f"with CNH histograms: {cnh_config.num_bins} bins of "
                   f"{cnh_config.bin_width_m * 100:.1f} cm over {near:.2f}-{far:.2f} m")
