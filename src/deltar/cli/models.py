"""``deltar check-official`` and ``deltar bench``: model parity and speed."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def _parse_size(text: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"must look like 480x640, got {text!r}",
                                 param_hint="--size") from None
    if height <= 0 or width <= 0 or height % 32 or width % 32:
        raise typer.BadParameter(f"needs positive multiples of 32, got {text!r}",
                                 param_hint="--size")
    return height, width


#: Memory one input pixel of one image takes in a forward pass, bytes: an upper
#: estimate (deltar-official measured about 0.7 KiB at 256x320, batch 4).
BENCH_BYTES_PER_PIXEL = 1024


def _resource_option(check, *args) -> None:
    """Run a resource check; its refusal (naming the option) is a usage error."""
    try:
        check(*args)
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None


def check_official_command(
    fixture: Path = typer.Argument(..., help="Parity fixture (.pt) with 'state_dict' and "
                                   "'cases', as official_parity_fixture_v2.pt."),
    threads: int = typer.Option(2, help="torch threads."),
) -> None:
    """Check that deltar-official reproduces the release's outputs stored in FIXTURE."""
    from rich.markup import escape
    from rich.table import Table

    from deltar.cli.progress import table_console
    from deltar.io.resources import check_threads
    from deltar.models.benchmark import (
        DEPTH_TOLERANCE_M,
        EDGE_TOLERANCE_M,
        check_official_fixture,
    )

    _resource_option(check_threads, threads, "--threads")
    try:
        results = check_official_fixture(fixture, threads=threads)
    except (OSError, ValueError) as error:
        raise typer.BadParameter(str(error), param_hint="FIXTURE") from None
    table = Table(title=escape(f"deltar-official vs release outputs ({fixture.name})"))
    table.add_column("case")
    table.add_column(f"max |depth error| m (tol {DEPTH_TOLERANCE_M:g})", justify="right")
    table.add_column(f"max |bin edge error| m (tol {EDGE_TOLERANCE_M:g})", justify="right")
    table.add_column("result")
    for result in results:
        table.add_row(result.name, f"{result.depth_max_error_m:.3g}",
                      f"{result.edges_max_error_m:.3g}",
                      "[green]pass[/green]" if result.passed else "[red]FAIL[/red]")
    table_console().print(table)
    typer.echo("what this checks: the network on the release's own inputs (its image, "
               "zone rectangles and sampled hypotheses) against the release's outputs at "
               "half resolution (the package's hypothesis sampling and its final resize "
               "for official weights are tested against the same file in its test suite)")
    if not all(result.passed for result in results):
        raise typer.Exit(code=1)


def bench_command(
    preset: str = typer.Option("deltar-official", help="Model preset."),
    size: str = typer.Option("480x640", help="Input size HxW (multiples of 32)."),
    batch: int = typer.Option(1, min=1, help="Batch size."),
    threads: int = typer.Option(2, min=1, help="torch threads."),
    repeats: int = typer.Option(10, min=1, help="Timed runs."),
    warmup: int = typer.Option(2, min=0, help="Untimed runs first."),
    optimize: bool = typer.Option(True, help="Apply the inference optimisations (folding, "
                                  "layout) before timing."),
    fold_encoder: bool = typer.Option(True, "--fold-encoder/--no-fold-encoder",
                                      help="Also fold the image encoder's batch norms."),
    channels_last: bool = typer.Option(True, help="Channels-last decoder and head."),
    matmul_size: int = typer.Option(2048, min=0, max=8192,
                                    help="Side of the float32 matrix product timed in the "
                                    "same process as the reference rate (0 skips it)."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the result as JSON."),
    overwrite: bool = typer.Option(False, help="Replace an existing --json file."),
) -> None:
    """Forward latency, peak memory, counted GFLOP and the fraction of the float32 matmul rate."""
    from rich.table import Table

    from deltar.cli.checks import output_file
    from deltar.cli.progress import table_console
    from deltar.io.atomic import write_text_atomic
    from deltar.io.resources import check_memory, check_threads
    from deltar.models.benchmark import benchmark_preset
    from deltar.models.presets import list_presets

    height, width = _parse_size(size)
    if preset not in list_presets():
        raise typer.BadParameter(f"unknown preset {preset!r}; known: {list_presets()}")
    if json_out is not None:  # a folder, or a file without --overwrite: before the runs
        output_file(json_out, "--json", overwrite)
    _resource_option(check_threads, threads, "--threads")
    _resource_option(check_memory, BENCH_BYTES_PER_PIXEL * batch * height * width,
                     f"--batch {batch} at {height}x{width}", "lower --batch or --size")
    result = benchmark_preset(preset, height, width, batch, threads, repeats, warmup, optimize,
                              fold_encoder, channels_last, matmul_size)
    table = Table(title="deltar bench")
    table.add_column("measure")
    table.add_column("value", justify="right")
    for key, value in result.items():
        table.add_row(key, str(value))
    table_console().print(table)
    if json_out is not None:
        write_text_atomic(json_out, json.dumps(result, indent=2) + "\n", overwrite=overwrite)
