"""``deltar evaluate`` (metrics of depth methods on a ZJU-L5- or THDR3K-layout set) and
``deltar wall-test`` (bias and jitter of an estimator against a flat wall)."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from deltar.cli.errors import fail
from deltar.cli.frame_options import CalibOption, check_calibration_fits, load_calibration
from deltar.cli.model_options import MODEL_OPTIONS, ModelOptions, model_options

#: Columns of the paper's ZJU-L5 table (metric key, header, higher is better).
_TABLE_COLUMNS = (("d1", "δ1 ↑", True), ("d2", "δ2 ↑", True), ("d3", "δ3 ↑", True),
                  ("rel", "REL ↓", False), ("rmse", "RMSE ↓", False),
                  ("log10", "log10 ↓", False))


#: Columns of methods that give a per-pixel sigma (a calibrated Gaussian: 0.683, 0.954).
_COVERAGE_COLUMNS = (("within_1sigma", "≤1σ"), ("within_2sigma", "≤2σ"))


def _metrics_table(result, title: str):
    """Rich table of the methods side by side, best value per column in bold."""
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=title)
    table.add_column("method")
    for _, header, _ in _TABLE_COLUMNS:
        table.add_column(header, justify="right")
    coverage = [(key, header) for key, header in _COVERAGE_COLUMNS
                if any(key in m for m in result.metrics.values())]
    for _, header in coverage:
        table.add_column(header, justify="right")
    table.add_column("s/frame", justify="right")
    best = {}
    for key, _, higher in _TABLE_COLUMNS:
        values = [m[key] for m in result.metrics.values()]
        best[key] = max(values) if higher else min(values)
    for name, metrics in result.metrics.items():
        cells = []
        for key, _, _ in _TABLE_COLUMNS:
            text = f"{metrics[key]:.3f}"
            cells.append(f"[bold]{text}[/bold]" if metrics[key] == best[key] else text)
        cells += [f"{metrics[key]:.3f}" if key in metrics else "-" for key, _ in coverage]
        table.add_row(escape(name), *cells, f"{result.seconds_per_frame[name]:.3f}")
    return table


def evaluate(
    method: str | None = typer.Option(
        None, "--method", "-m",
        help="Comma-separated method names, or 'all' for every classical baseline; "
             "'<baseline>+far' (e.g. bilinear+far) reads zones with no target at 5 m."),
    checkpoint: list[str] = typer.Option(
        [], "--checkpoint", "-c",
        help="A trained model to evaluate beside the methods: a bundled name ('default') "
             "or a checkpoint file (repeatable); reported as 'model:NAME'."),
    official: Path | None = typer.Option(
        None, "--official", help="The officially released weights (e.g. nyu.pt); "
        "reported as 'official:PATH'."),
    data: Path = typer.Option(..., "--data", help="data.json of a ZJU-L5-layout set, or "
                              "the file list of a THDR3K-layout set (detected)."),
    split: str = typer.Option("test", "--split", help="Split (key) in data.json."),
    json_out: Path | None = typer.Option(
        None, "--json", help="Write {method: metrics} here (JSON, atomic)."),
    save_vis: Path | None = typer.Option(
        None, "--save-vis", help="Write a PNG panel per frame and method into this folder."),
    limit: int | None = typer.Option(None, "--limit", min=1,
                                     help="Evaluate only the first N frames."),
    min_depth: float = typer.Option(1e-3, "--min-depth", help="Ground truth must be > this (m)."),
    max_depth: float = typer.Option(10.0, "--max-depth", help="Ground truth must be < this (m)."),
    flip: bool = typer.Option(False, "--flip", help="Also evaluate each --checkpoint and "
                              "--official model with test-time flip averaging (reported "
                              "as 'model:NAME+flip')."),
    network: bool = typer.Option(False, "--network", help="Also evaluate each --checkpoint "
                                 "model without the estimator's confidence blend with the "
                                 "colorization fill: the network's own depth (reported as "
                                 "'model:NAME+network'; the released weights never blend)."),
    keep_going: bool = typer.Option(False, "--keep-going", help="Leave out a frame that "
                                    "would stop the run (zones that cannot be a real "
                                    "reading, a method that refuses it) for every method and "
                                    "go on; the table counts them (exit code 1 if any)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --json "
                                   "file and --save-vis panels."),
) -> None:
    """Evaluate depth methods on a ZJU-L5-layout set and print the paper's metrics table.

    Metrics are computed per frame over pixels with ground truth in (min-depth,
    max-depth) metres and averaged over frames, as in the official release.
    """
    from rich.markup import escape

    from deltar.cli.checks import output_file, output_folder
    from deltar.cli.progress import ProgressReport, table_console
    from deltar.data.zone_sets import open_zone_set
    from deltar.evaluation.model_methods import method_input_files
    from deltar.evaluation.runner import create_predictor, evaluate_methods, resolve_method_names
    from deltar.evaluation.visualize import safe_filename, save_frame_panel
    from deltar.io.atomic import write_text_atomic
    from deltar.io.input_file import refuse_input_as_output

    console = table_console()
    specs = [m for m in (method or "").split(",") if m.strip()]
    models = [f"model:{c}" for c in checkpoint]
    if official is not None:
        models.append(f"official:{official}")
    for on, option, what in ((flip, "--flip", "--checkpoint or --official"),
                             (network, "--network", "--checkpoint")):
        if on and not (models if option == "--flip" else checkpoint):
            raise typer.BadParameter(f"{option} adds a variant of each {what} model; give "
                                     "one (for the bundled model: --checkpoint default)",
                                     param_hint=option)
    flipped = [f"{m}+flip" for m in models] if flip else []
    networks = [f"model:{c}+network" for c in checkpoint] if network else []
    specs += models + flipped + networks
    checkpoint_names = {n for n in models + flipped + networks if n.startswith("model:")}
    official_names = {n for n in models + flipped if n.startswith("official:")}
    if not specs:
        raise typer.BadParameter("give --method, --checkpoint or --official",
                                 param_hint="--method")
    if not 0 < min_depth < max_depth < float("inf"):
        raise typer.BadParameter(f"need 0 < --min-depth < --max-depth (metres, finite), got "
                                 f"{min_depth:g} and {max_depth:g}",
                                 param_hint="--min-depth/--max-depth")
    try:
        names = resolve_method_names(specs)
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="--method") from err
    try:
        dataset = open_zone_set(data, split=split)
    except (OSError, ValueError) as err:
        raise typer.BadParameter(str(err), param_hint="--data") from err
    if len(dataset) == 0:
        raise typer.BadParameter(f"split {split!r} of {data} lists no frames",
                                 param_hint="--data")
    total = len(dataset) if limit is None else min(limit, len(dataset))
    # A missing frame file fails now, not after predicting the frames before it.
    for index in range(total):
        for path in dataset.frame_files(index):
            if not path.is_file():
                index_file = data / "data.json" if data.is_dir() else data
                raise typer.BadParameter(f"frame file not found: {path} (frame "
                                         f"{dataset.filenames[index]!r} of {index_file})",
                                         param_hint="--data")
    # The set's files and every method's model files: no output replaces either.
    inputs = [*_set_files(dataset, data), *(f for n in names for f in method_input_files(n))]
    if json_out is not None:
        refuse_input_as_output(json_out, inputs, "--json")
        output_file(json_out, "--json", overwrite)
    if save_vis is not None:
        # A folder of panels may not lie inside the set's folder either.
        refuse_input_as_output(save_vis, [*inputs, dataset.root], "--save-vis", folder=True)
        output_folder(save_vis, "--save-vis")
        used = [save_vis / safe_filename(name) for name in names
                if (save_vis / safe_filename(name)).is_dir()
                and any((save_vis / safe_filename(name)).iterdir())]
        if used and not overwrite:
            raise FileExistsError(f"--save-vis: {used[0]} already holds panels; pass "
                                  "--overwrite to replace them or choose another folder")
    predictors = {}
    for name in names:
        try:
            predictors[name] = create_predictor(name)
        except (OSError, ValueError) as err:  # named as the option that gave the method
            option = ("--checkpoint" if name in checkpoint_names else
                      "--official" if name in official_names else "--method")
            raise typer.BadParameter(str(err), param_hint=option) from err

    with ProgressReport("evaluating", total=total) as progress:

        def on_frame(index, sample, predictions) -> None:
            if save_vis is not None:
                for name, depth in predictions.items():
                    target = save_vis / safe_filename(name) / f"{safe_filename(sample.name)}.png"
                    save_frame_panel(target, sample, depth, name, max_depth_m=None)
            progress.advance()

        try:
            result = evaluate_methods(dataset, predictors, min_depth=min_depth,
                                      max_depth=max_depth, limit=limit, on_frame=on_frame,
                                      keep_going=keep_going)
        except ValueError as err:
            if not keep_going:
                raise
            fail(err)  # every frame was left out: nothing to score

    title = escape(f"{data} (split {split}): {result.frames} frames")
    if result.skipped:
        title += f" ({result.skipped} without valid ground truth skipped)"
    if result.refused:
        title += f" ({len(result.refused)} left out, --keep-going)"
    console.print(_metrics_table(result, title))
    if json_out is not None:
        write_text_atomic(json_out, json.dumps(result.metrics, indent=2) + "\n",
                          overwrite=overwrite)
        typer.echo(f"metrics written to {json_out}")
    if save_vis is not None:
        typer.echo(f"visualisations written to {save_vis}")
    if result.refused:
        fail(f"{len(result.refused)} of {total} frames left out (first: "
             f"{result.refused[0][1]})")


def _set_files(dataset, data: Path) -> list[Path]:
    """The input files of an evaluated set: its index and each frame's file(s)."""
    index = data / "data.json" if data.is_dir() else data
    files = [index]
    for rel in dataset.filenames:
        frame = dataset.root / rel
        # ZJU-L5: one .h5 file per frame; THDR3K: files named <frame>_<kind>.<ext>.
        files += [frame, *frame.parent.glob(f"{frame.name}_*")]
    return files


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
    from rich.markup import escape
    from rich.table import Table

    from deltar.cli.checks import existing_outputs, output_folder
    from deltar.cli.progress import table_console
    from deltar.evaluation.wall_test import result_paths, wall_test, write_results
    from deltar.io.input_file import refuse_input_as_output
    from deltar.io.recording import Recording

    model.check()
    resolved = [folder.resolve() for folder in recordings]
    twice = next((folder for folder, path in zip(recordings, resolved, strict=True)
                  if resolved.count(path) > 1), None)
    if twice is not None:
        raise typer.BadParameter(f"{twice} is given more than once; each recording is one "
                                 "wall distance", param_hint="RECORDINGS")
    for folder in recordings:
        Recording(folder)  # a missing or corrupt recording fails before the model
    refuse_input_as_output(out, [*recordings, calib], "--out", folder=True)
    for path in result_paths(out).values():
        refuse_input_as_output(path, [calib, *model.input_files()], "--out")
    output_folder(out, "--out")
    if not overwrite:  # before the model and the frames, not after them
        existing_outputs(result_paths(out).values())
    calibration = load_calibration(calib)  # a bad --calib fails before the model
    if calibration is not None:  # and one for another resolution or grid
        for folder in recordings:
            check_calibration_fits(calibration, calib, Recording(folder).meta, folder)
    try:
        estimator = model.load()
        results = wall_test(recordings, estimator, calibration=calibration,
                            every=every, limit=limit)
        paths = write_results(out, results, title=estimator.weights, overwrite=overwrite)
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        fail(err)
    table = Table(title=escape(f"flat wall ({estimator.weights})"))
    for column in ("distance m", "frames", "plane from", "net bias mm", "net jitter mm",
                   "zones bias mm", "zones jitter mm"):
        table.add_column(column, justify="right")
    for r in results:
        table.add_row(f"{r.distance_m:.3f}", str(r.frames), r.reference,
                      f"{1000 * r.network_bias_m:.1f}", f"{1000 * r.network_jitter_m:.1f}",
                      f"{1000 * r.zones_bias_m:.1f}", f"{1000 * r.zones_jitter_m:.1f}")
    table_console().print(table)
    typer.echo(f"wrote {', '.join(str(p) for p in paths.values())}")
