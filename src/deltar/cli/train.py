"""``deltar train``: train or fine-tune DELTAR from a YAML configuration."""

from __future__ import annotations

from pathlib import Path

import typer


def train_command(
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML training config "
                                       "(e.g. configs/cross_scene_select.yaml)."),
    override: list[str] | None = typer.Option(None, "--override", "-o", help="Dotted "
                                              "key=value replacing a config entry, e.g. "
                                              "optim.lr=1e-4 (repeatable)."),
    run_dir: Path | None = typer.Option(None, "--run-dir", help="Run folder (default: "
                                        "<output_dir>/<name>-<UTC time>); required for "
                                        "torchrun / SLURM launches."),
    resume: Path | None = typer.Option(None, "--resume", help="Continue the run in this "
                                       "folder from checkpoints/last.ckpt, with its saved "
                                       "config.yaml."),
    print_config: bool = typer.Option(False, "--print-config", help="Print the resolved "
                                      "config as YAML and exit."),
) -> None:
    """Train DELTAR (Lightning): checkpoints, TensorBoard/CSV logs and config in a run folder."""
    from deltar.training.config import load_config

    if resume is not None:
        if config is not None or override or run_dir is not None:
            raise typer.BadParameter("--resume takes the run's own config.yaml; do not pass "
                                     "--config, --override or --run-dir with it")
        config = resume / "config.yaml"
        run_dir = resume
    if config is None:
        raise typer.BadParameter("give --config FILE (or --resume RUN_DIR)")
    try:
        cfg = load_config(config, override or ())
    except (FileNotFoundError, ValueError) as err:
        raise typer.BadParameter(str(err)) from err
    if print_config:
        typer.echo(cfg.to_yaml())
        return
    from deltar.training.run import train

    # Missing data / weights or an occupied run folder reach the user as one error line.
    folder = train(cfg, run_dir, resume=resume is not None)
    typer.echo(f"run folder: {folder}")
