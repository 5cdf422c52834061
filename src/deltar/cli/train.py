"""``deltar train``: train or fine-tune DELTAR from a YAML configuration."""

from __future__ import annotations

import math
import os
from pathlib import Path

import typer

#: --detector-noise's default: the degraded sets of ``deltar simulate --drop-fraction 0.2
#: --bias-prob 0.3`` (its bias defaults).
_DEFAULT_DETECTOR_NOISE = "0.2,0.3,0.10,0.15"


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
    from deltar.extras import require_extra

    for module in ("torch", "lightning"):  # one line naming the 'train' extra
        require_extra(module, "deltar train", "train")
    from deltar.training.config_loading import load_config

    if resume is not None:
        if config is not None or override or run_dir is not None:
            raise typer.BadParameter("--resume takes the run's own config.yaml; do not pass "
                                     "--config, --override or --run-dir with it")
        config = resume / "config.yaml"
        run_dir = resume
    if config is None:
        raise typer.BadParameter("give --config FILE (or --resume RUN_DIR)")
    if run_dir is not None and run_dir.exists() and not run_dir.is_dir():
        raise typer.BadParameter(f"{run_dir} is a file; a run folder is a folder",
                                 param_hint="--resume" if resume is not None else "--run-dir")
    try:
        cfg = load_config(config, override or ())
    except (OSError, ValueError) as err:
        raise typer.BadParameter(str(err)) from err
    if print_config:
        typer.echo(cfg.to_yaml())
        return
    _check_machine(cfg.trainer)
    from deltar.training.run import RUN_DIR_ENV, TrainingInterrupted, train

    _check_run_folder(run_dir, resume is not None, cfg.output_dir, os.environ.get(RUN_DIR_ENV))

    # Missing data / weights or an occupied run folder reach the user as one error line.
    try:
        folder = train(cfg, run_dir, resume=resume is not None)
    except TrainingInterrupted as stop:  # a scheduler's requeue script reads the status
        from deltar.cli.errors import fail, received_signal

        # The CLI's SIGTERM handler stops Lightning as Ctrl+C does: name the real signal.
        name = received_signal() or stop.signal_name
        if name != stop.signal_name:
            stop = TrainingInterrupted(stop.run_dir, name, stop.step)
        fail(stop, stop.exit_code)
    typer.echo(f"run folder: {folder}")


def _check_run_folder(run_dir: Path | None, resume: bool, output_dir: str,
                      inherited: str | None) -> None:
    """The run folder (``--run-dir``, or a new one in the config's ``output_dir``) can be
    made: no file on its path and, for a new run, a folder a file can be written in,
    before the network and the data are built.

    Raises:
        typer.BadParameter: naming the option or key.
    """
    from deltar.cli.checks import output_folder

    if run_dir is None and inherited:  # a process Lightning launched: its parent checked
        return
    option = "--resume" if resume else ("--run-dir" if run_dir is not None else "output_dir")
    folder = Path(output_dir) if run_dir is None else run_dir
    try:
        if not resume:
            output_folder(folder, option)
        # A finished run resumes from a read-only folder (it writes nothing): no probe.
        elif folder.exists() and not folder.is_dir():
            raise ValueError(f"{option} {folder} is a file, not a folder")
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None


def _check_machine(trainer) -> None:
    """The config's ``trainer.devices`` and ``num_threads`` against this machine.

    Raises:
        typer.BadParameter: more devices (CUDA GPUs, or CPU processes) or threads than
            this machine has, naming the config key.
    """
    import torch

    from deltar.io.resources import check_threads, cpu_count

    try:
        if trainer.num_threads is not None:
            check_threads(trainer.num_threads, "trainer.num_threads")
    except ValueError as err:
        raise typer.BadParameter(str(err)) from None
    launched = ("WORLD_SIZE", "MASTER_ADDR", "SLURM_NTASKS", "TORCHELASTIC_RUN_ID",
                "LSB_JOBID", "OMPI_COMM_WORLD_SIZE", "PMI_SIZE")  # Lightning's launchers
    if trainer.num_nodes > 1 and not any(name in os.environ for name in launched):
        # Started by hand, each process would wait for the other nodes forever.
        raise typer.BadParameter(f"trainer.num_nodes is {trainer.num_nodes}: start each node "
                                 "with a launcher (torchrun --nnodes, or srun under SLURM; "
                                 "docs/training.md), which sets WORLD_SIZE / MASTER_ADDR")
    if not isinstance(trainer.devices, int):
        return
    gpu = trainer.accelerator in ("gpu", "cuda") or (trainer.accelerator == "auto"
                                                      and torch.cuda.is_available())
    have = torch.cuda.device_count() if gpu else cpu_count()
    if trainer.devices > have:
        kind = "CUDA GPU(s)" if gpu else "CPUs"
        raise typer.BadParameter(f"trainer.devices is {trainer.devices} but this machine has "
                                 f"{have} {kind} (trainer.accelerator "
                                 f"{trainer.accelerator!r})")


def fit_uncertainty_command(
    checkpoint: str = typer.Argument(..., help="A deltar checkpoint file, or a bundled "
                                     "name ('default')."),
    data: list[Path] = typer.Option(..., "--data", help="A set with ground truth "
                                    "(data.json of a ZJU-L5-layout set, e.g. from deltar "
                                    "simulate) of the model's TRAINING scenes (repeatable)."),
    out: Path = typer.Option(..., "--out", help="The calibrated checkpoint to write (a new "
                             "file)."),
    frames_per_set: int | None = typer.Option(None, "--frames-per-set", min=1,
                                              help="At most this many frames of each set, "
                                              "spread evenly (default: all)."),
    pixels_per_frame: int = typer.Option(4000, "--pixels-per-frame", min=100,
                                         help="Random pixels with ground truth per frame."),
    blend_objective: str = typer.Option("relative", "--blend-objective",
                                        help="What the blend's fit minimises: 'relative' "
                                        "(a smoothed absolute log error, about REL) or "
                                        "'squared' (squared log error, weighs large errors "
                                        "more)."),
    detector_data: list[Path] = typer.Option([], "--detector-data", help="A set of the "
                                             "training scenes whose zones are right (a "
                                             "clean simulation; repeatable): a detector of "
                                             "biased zones is trained on it and joins the "
                                             "outlier candidates."),
    detector_noise: str = typer.Option(_DEFAULT_DETECTOR_NOISE, "--detector-noise",
                                       help="The degradation the detector learns, "
                                       "'DROP,PROB,MEAN,STD' as deltar simulate's "
                                       "--drop-fraction, --bias-prob, --bias-mean, "
                                       "--bias-std (metres)."),
    split: str = typer.Option("test", "--split", help="Split (key) of each --data and "
                              "--detector-data set to read (deltar simulate --split)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out."),
) -> None:
    """Fit a model's output stage on frames with ground truth: outliers, blend, sigma, flags.

    It first chooses when the estimator sets aside zones that disagree with every
    neighbour (a noisy sensor's outliers; or never), by the error on these frames; with
    --detector-data a learned detector of biased zones is among the choices. For
    a plane-select model (the bundled default's kind) it then fits how the estimator
    blends the network's depth with the zones' colorization fill, then (every
    model) how it turns the network's spread into a sigma that holds 68% of the errors
    within one sigma and 95% within two (inside and beyond the zone grid), and writes the
    checkpoint with both; deltar predict and the estimator then use them. For a model
    that reads no-target flags it also chooses, on the same frames with their flags
    removed, when a reading without flags (e.g. a ZJU-L5 file) has an invalid zone read
    as no target (beside a valid zone reading at least a fitted distance). Give frames of
    the model's training scenes (clean and degraded), never of the scenes you will judge
    it on.
    """
    from deltar.cli.checks import output_file
    from deltar.cli.progress import ProgressReport
    from deltar.data.zone_sets import open_zone_set
    from deltar.evaluation.uncertainty import fit_checkpoint_uncertainty
    from deltar.inference.blend_fit import BLEND_OBJECTIVES
    from deltar.io.input_file import refuse_input_as_output

    if blend_objective not in BLEND_OBJECTIVES:
        raise typer.BadParameter(f"must be one of {', '.join(BLEND_OBJECTIVES)}, got "
                                 f"{blend_objective!r}", param_hint="--blend-objective")
    noise = _detector_noise(detector_noise)
    if detector_noise != _DEFAULT_DETECTOR_NOISE and not detector_data:
        raise typer.BadParameter("describes the noise of the detector --detector-data trains; "
                                 "give --detector-data too", param_hint="--detector-noise")
    from deltar.inference.loading import resolve_source

    try:
        resolve_source(checkpoint, "checkpoint")  # refuses a Lightning .ckpt, as elsewhere
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="CHECKPOINT") from err
    refuse_input_as_output(out, [Path(checkpoint), *data, *detector_data], "--out")
    output_file(out, "--out", overwrite)
    try:
        sets = [open_zone_set(path, split) for path in data]
    except (OSError, ValueError) as err:
        raise typer.BadParameter(str(err), param_hint="--data") from err
    try:
        detector_sets = [open_zone_set(path, split) for path in detector_data]
    except (OSError, ValueError) as err:
        raise typer.BadParameter(str(err), param_hint="--detector-data") from err
    for option, paths, opened in (("--data", data, sets),
                                  ("--detector-data", detector_data, detector_sets)):
        empty = next((path for path, s in zip(paths, opened, strict=True) if not len(s)), None)
        if empty is not None:  # it would be left out without a word
            raise typer.BadParameter(f"split {split!r} of {empty} lists no frames",
                                     param_hint=option)
    frames = sum(len(s) if frames_per_set is None else min(len(s), frames_per_set)
                 for s in sets)
    with ProgressReport("fitting the output stage") as progress:
        # Each frame is visited three times (outlier rule; zone consistency; blend and
        # sigma), five for a network that reads no-target flags (its depth and rule too).
        fit = fit_checkpoint_uncertainty(checkpoint, sets, out, frames_per_set=frames_per_set,
                                         pixels_per_frame=pixels_per_frame,
                                         overwrite=overwrite, blend_objective=blend_objective,
                                         detector_sets=detector_sets, detector_noise=noise,
                                         on_frame=progress.advance,
                                         on_passes=lambda passes: progress.set_total(
                                             passes * frames))
    if fit.outlier_errors:
        tried = ", ".join(f"{_rule_text(c, short=True)} {e:.4f}"
                          for c, e in fit.outlier_errors.items())
        typer.echo(f"zone outliers: {_rule_text(fit.outlier_rule)} (mean relative error "
                   f"where a candidate sets a zone aside; rules by tolerance / fewest "
                   f"outliers, the detector by probability: {tried})")
    if fit.zone_consistency_errors:
        tried = ", ".join(f"{c:g} {e:.4f}" for c, e in fit.zone_consistency_errors.items())
        typer.echo(f"zone consistency: {fit.zone_consistency:g} (mean relative error of each "
                   f"strength: {tried})")
    if fit.no_target_depth_errors:
        tried = ", ".join(f"{c:g} m {e:.4f}" for c, e in fit.no_target_depth_errors.items())
        typer.echo(f"zones that reported no target read at {fit.no_target_depth_m:g} m (mean "
                   f"relative error on frames with such zones: {tried})")
    if fit.blend is not None:
        for name in ("inside", "outside"):
            region = getattr(fit.blend, name)
            sign = "-" if region.spread_slope < 0 else "+"
            typer.echo(f"blend {name} the zone grid: w = sigmoid({region.bias:.3f} {sign} "
                       f"{abs(region.spread_slope):.3f} log(spread/depth))")
        rel = fit.relative_error
        typer.echo(f"mean relative error on these pixels: network {rel['network']:.4f}, "
                   f"fill {rel['fill']:.4f}, blend {rel['blend']:.4f}")
    for name in ("inside", "outside"):
        region = getattr(fit.calibration, name)
        raw, new = fit.raw_coverage[name], fit.coverage[name]
        typer.echo(f"{name} the zone grid ({fit.pixels[name]} pixels): sigma^2 = "
                   f"({region.spread:.3f} spread)^2 + ({region.floor:.4f} depth)^2 + "
                   f"({region.disagreement:.3f} |blend move|)^2; within 1/2 sigma "
                   f"{raw[0]:.1%} / {raw[1]:.1%} raw -> {new[0]:.1%} / {new[1]:.1%}")
    if fit.no_target_errors:
        tried = ", ".join(f"{'none' if c is None else f'{c:g} m'} {e:.4f}"
                          for c, e in fit.no_target_errors.items())
        chosen = fit.no_target_min_neighbour_m
        typer.echo("frames without no-target flags: invalid zones read as no target "
                   + ("never" if chosen is None else f"beside a valid zone reading >= "
                      f"{chosen:g} m") + f" (mean relative error with flags removed: {tried})")
    typer.echo(f"wrote {fit.path} ({fit.frames} frames)")


def _detector_noise(text: str) -> dict[str, float]:
    """--detector-noise 'DROP,PROB,MEAN,STD' as ``fit_outlier_detector``'s arguments."""
    try:
        drop, prob, mean, std = (float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"must be four numbers 'DROP,PROB,MEAN,STD', got {text!r}",
                                 param_hint="--detector-noise") from None
    if not (0 <= drop < 1 and 0 < prob <= 1 and math.isfinite(mean) and
            math.isfinite(std) and std >= 0):
        raise typer.BadParameter(f"needs DROP in [0, 1), PROB in (0, 1], MEAN finite and "
                                 f"STD >= 0, got {text!r}", param_hint="--detector-noise")
    return {"drop_fraction": drop, "bias_prob": prob, "bias_mean_m": mean,
            "bias_std_m": std}


def _rule_text(rule, short: bool = False) -> str:
    """A zone outlier rule or detector in words (None: every zone kept)."""
    from deltar.sensor.zone_outlier_detector import OutlierDetector

    if rule is None:
        return "kept" if short else "every zone kept"
    if isinstance(rule, OutlierDetector):
        return f"detector > {rule.threshold:g}" if short else \
            f"set aside where the learned detector gives > {rule.threshold:g}"
    if short:
        return f"{rule.tolerance:g} / {rule.min_zones}"
    return (f"set aside beyond {rule.tolerance:g} log distance of all neighbours, in "
            f"frames with >= {rule.min_zones} such zones")
