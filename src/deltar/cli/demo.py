"""``deltar demo``: the whole path on generated scenes, with nothing to download.

Renders procedural rooms (the package bundles no third-party images), simulates the
L5 zone readings, runs every classical baseline (and the bundled model when the package
ships one), and writes per-frame panels, the metrics table and a JSON of the metrics.
"""

from __future__ import annotations

from pathlib import Path

import typer

from deltar.cli.main import app


def bundled_model_methods() -> list[str]:
    """Evaluation method names of the models this installation ships (may be empty)."""
    try:
        from deltar.evaluation.runner import resolve_method_names

        return resolve_method_names("model:default")
    except (ImportError, ValueError):
        return []


@app.command("demo")
def demo(
    out: Path = typer.Argument(Path("deltar-demo"), help="Output folder (created; must not "
                               "already hold a demo)."),
    frames: int = typer.Option(6, "--frames", min=1, help="Number of generated scenes."),
    seed: int = typer.Option(2022, "--seed", help="Seed of the procedural scenes."),
    size: str = typer.Option("480x640", "--size", help="Image size HxW in pixels."),
) -> None:
    """Simulate L5 readings over generated rooms and compare depth methods on them.

    Writes OUT/scenes (a ZJU-L5-layout set), OUT/panels (one PNG per frame and method),
    and OUT/metrics.json; prints the paper's metrics table.
    """
    from deltar.cli.evaluate import evaluate
    from deltar.cli.simulate import simulate_command

    scenes = out / "scenes"
    if (scenes / "data.json").exists():
        raise typer.BadParameter(f"{out} already holds a demo; choose another folder",
                                 param_hint="OUT")
    simulate_command(src=f"procedural:{frames}:{seed}:{size}", out=scenes, grid=8,
                     layout="calibrated", start=0, stop=None, step=1, limit=None,
                     depth_scale=None, intrinsics=None, split="test")
    methods = ",".join(["all", *bundled_model_methods()])
    evaluate(method=methods, data=scenes / "data.json", split="test",
             json_out=out / "metrics.json", save_vis=out / "panels", limit=None,
             min_depth=1e-3, max_depth=10.0)
