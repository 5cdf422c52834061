"""Run a training from a :class:`TrainConfig`: run folder, trainer, callbacks, resume.

A run folder holds::

    config.yaml            the full configuration (every hyper-parameter)
    checkpoints/last.ckpt  newest checkpoint (every N steps and at epoch ends)
    checkpoints/step=*.ckpt  the newest few step checkpoints
    logs/                  TensorBoard events and metrics.csv (a resume appends to both)
    history/rank<r>.jsonl  per-step loss and the dataset indices each process trained on
    history/rank<r>_final.json  final step and a digest of the weights of each process
    model.pt               the trained network (EMA weights when enabled)

Every file is written atomically, so a run killed at any moment leaves only complete
files, and ``train(..., resume=True)`` continues from ``checkpoints/last.ckpt``, also in a
folder moved or copied since (:mod:`deltar.training.run_folder`). A run stopped by SIGTERM
or Ctrl+C raises :class:`TrainingInterrupted` (Lightning would end it as a success).
"""

from __future__ import annotations

import math
import os
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, EMAWeightAveraging

from deltar.io.atomic import atomic_path, leftover_temporaries, write_text_atomic
from deltar.io.torch_file import read_torch_file
from deltar.training.config import TrainConfig
from deltar.training.config_loading import config_from_dict
from deltar.training.data import DeltarDataModule
from deltar.training.module import DeltarSystem, export_model, initial_weights
from deltar.training.run_folder import (
    CHECKPOINT_CONFIG_KEY,
    AtomicCheckpointIO,
    RunCheckpoints,
    RunConfigRecord,
    TrainingHistory,
    appending_csv_logger,
    config_changes,
    network_mismatch,
)

CONFIG_NAME = "config.yaml"
LAST_CHECKPOINT = "last.ckpt"
#: Environment variable carrying the run folder to processes launched by Lightning.
RUN_DIR_ENV = "DELTAR_RUN_DIR"


class TrainingInterrupted(RuntimeError):
    """A run stopped by a signal (SIGTERM from a scheduler, Ctrl+C) before it finished.

    Attributes:
        signal_name: ``"SIGTERM"`` or ``"SIGINT"``.
        exit_code: the conventional status for it (128 + the signal's number).
    """

    def __init__(self, run_dir: Path, signal_name: str, step: int) -> None:
        import signal

        self.run_dir, self.signal_name, self.step = run_dir, signal_name, step
        self.exit_code = 128 + int(getattr(signal, signal_name))
        last = run_dir / "checkpoints" / LAST_CHECKPOINT
        where = (f"its newest checkpoint is {last}: continue with `deltar train --resume "
                 f"{run_dir}`") if last.is_file() else ("it stopped before its first "
                                                         "checkpoint: remove the folder "
                                                         "and start it again")
        super().__init__(f"run {run_dir} stopped by {signal_name} at step {step}, before it "
                         f"finished (no model.pt written); {where}")


def new_run_dir(config: TrainConfig) -> Path:
    """``<output_dir>/<name>-<UTC timestamp>`` (not created)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    return Path(config.output_dir) / f"{config.name}-{stamp}"


def load_run_config(run_dir: str | Path) -> TrainConfig:
    """The configuration saved in a run folder.

    Raises:
        FileNotFoundError: the folder has no ``config.yaml``.
    """
    import yaml

    path = Path(run_dir) / CONFIG_NAME
    if not path.is_file():
        raise FileNotFoundError(f"no {CONFIG_NAME} in run folder {run_dir}")
    return config_from_dict(yaml.safe_load(path.read_text(encoding="utf-8")))


def build_system(config: TrainConfig, starting_weights: bool = True) -> DeltarSystem:
    """The Lightning module with the configured network and, with ``starting_weights``,
    its starting weights (``model.encoder_weights``, ``official_weights`` or
    ``init_checkpoint``; a resumed run takes every weight from its checkpoint, so the
    files it started from may since have moved or gone)."""
    fresh = not (config.model.official_weights or config.model.init_checkpoint)
    system = DeltarSystem(config.model.preset, config.model.overrides, config.optim,
                          encoder_weights=config.model.encoder_weights
                          if fresh and starting_weights else None,
                          allow_download=config.model.allow_download)
    if not starting_weights:
        return system
    if config.model.official_weights:
        from deltar.models import load_official_weights

        load_official_weights(system.model, config.model.official_weights)
    elif config.model.init_checkpoint:
        initial_weights(system.model, config.model.init_checkpoint, config.model.preset)
    return system


def build_data_module(config: TrainConfig, system: DeltarSystem) -> DeltarDataModule:
    """The run's data, drawn as the network's input contract says: the image
    normalisation and whether hypotheses come from zone histograms."""
    return DeltarDataModule(config.data, config.seed, system.model.network_config.inputs)


def build_trainer(config: TrainConfig, run_dir: Path,
                  extra_callbacks: list[Callback] | tuple[Callback, ...] = ()) -> L.Trainer:
    """A Lightning trainer for the configuration, writing into ``run_dir``.

    ``extra_callbacks`` are appended to the standard ones (checkpoints, history, lr
    monitor, progress bar, EMA).
    """
    from lightning.pytorch.callbacks import LearningRateMonitor, RichProgressBar
    from lightning.pytorch.loggers import TensorBoardLogger

    tcfg = config.trainer
    checkpoints = RunCheckpoints(
        dirpath=run_dir / "checkpoints", filename="step={step}", auto_insert_metric_name=False,
        every_n_train_steps=tcfg.checkpoint_every_n_steps, save_top_k=tcfg.keep_checkpoints,
        monitor="step", mode="max", save_last=True)
    callbacks: list[Callback] = [checkpoints, RunConfigRecord(config),
                                 TrainingHistory(run_dir / "history"),
                                 LearningRateMonitor(logging_interval="step"),
                                 *extra_callbacks]
    if tcfg.progress_bar:
        callbacks.append(RichProgressBar())
    if config.ema.enabled:
        callbacks.append(EMAWeightAveraging(decay=config.ema.decay,
                                            update_starting_at_step=config.ema.start_step))
    loggers = [TensorBoardLogger(run_dir / "logs", name="", version="tensorboard"),
               appending_csv_logger(run_dir / "logs", "csv")]
    return L.Trainer(
        accelerator=tcfg.accelerator, devices=tcfg.devices, num_nodes=tcfg.num_nodes,
        strategy=tcfg.strategy, precision=tcfg.precision,
        sync_batchnorm=config.model.sync_batchnorm,
        max_epochs=tcfg.max_epochs, max_steps=tcfg.max_steps,
        gradient_clip_val=config.optim.grad_clip_norm, gradient_clip_algorithm="norm",
        check_val_every_n_epoch=tcfg.val_every_n_epochs, val_check_interval=tcfg.val_check_interval,
        limit_train_batches=tcfg.limit_train_batches, limit_val_batches=tcfg.limit_val_batches,
        log_every_n_steps=tcfg.log_every_n_steps, deterministic=tcfg.deterministic,
        enable_progress_bar=tcfg.progress_bar, callbacks=callbacks, logger=loggers,
        plugins=[AtomicCheckpointIO()], use_distributed_sampler=False,
        num_sanity_val_steps=0, default_root_dir=run_dir)


def _refuse_run_dir_in_inputs(config: TrainConfig, run_dir: Path, option: str) -> None:
    """A run folder is an output: not a data source's folder nor inside one (a set's
    folder for a ``data.json`` or file list), nor a starting-weights file."""
    from deltar.io.input_file import refuse_input_as_output
    from deltar.training.config import ZONE_SET_SOURCE_KINDS

    inputs: list[Path | None] = []
    for source in config.data.sources:
        if source.path:
            path = Path(source.path)
            inputs.append(path.parent if source.kind in ZONE_SET_SOURCE_KINDS and
                          path.is_file() else path)
    model = config.model
    inputs += [Path(p) for p in (model.init_checkpoint, model.official_weights,
                                 model.encoder_weights) if p]
    refuse_input_as_output(run_dir, inputs, option, folder=True)


def train(config: TrainConfig, run_dir: str | Path | None = None, resume: bool = False,
          extra_callbacks: list[Callback] | tuple[Callback, ...] = ()) -> Path:
    """Train (or resume) a run.

    Args:
        config: the validated configuration.
        run_dir: run folder; None makes a new one under ``config.output_dir``. A new run
            refuses a folder that already holds a ``config.yaml``.
        resume: continue the run in ``run_dir`` from ``checkpoints/last.ckpt``, with the
            optimiser, schedule, step, data position and RNG states; its saved
            ``config.yaml`` must equal ``config``.
        extra_callbacks: more Lightning callbacks for this run.

    Returns:
        The run folder.

    Raises:
        FileExistsError: a new run would overwrite an existing run folder's config.
        FileNotFoundError: resuming without a checkpoint.
        ValueError: resuming with a configuration that differs from the saved one.
    """
    given = run_dir is not None
    run_dir = Path(run_dir) if given else _default_run_dir(config)
    if not resume:  # a run kept where it was made resumes there
        _refuse_run_dir_in_inputs(config, run_dir, "run_dir" if given else "output_dir")
    config_path = run_dir / CONFIG_NAME
    checkpoint = run_dir / "checkpoints" / LAST_CHECKPOINT
    if resume:
        if not checkpoint.is_file():
            stopped = " (the run stopped before its first checkpoint: remove the folder " \
                "and start the run again)" if config_path.is_file() else ""
            raise FileNotFoundError(f"nothing to resume: {checkpoint} does not exist{stopped}")
        if load_run_config(run_dir).to_dict() != config.to_dict():
            raise ValueError(f"config differs from the one saved in {config_path}; resume "
                             "with the run's own config.yaml")
    if config.trainer.num_threads is not None:
        torch.set_num_threads(config.trainer.num_threads)
    L.seed_everything(config.seed, workers=True, verbose=False)
    system = build_system(config, starting_weights=not resume)
    data = build_data_module(config, system)
    data.setup()
    trainer = build_trainer(config, run_dir, extra_callbacks)
    system.schedule_steps = count_training_steps(config, len(data.train_set), trainer.world_size)
    _check_validation_limits(config, data, trainer)
    if resume and resumed_run_finished(checkpoint, system.schedule_steps, config, system):
        # Nothing left to train (e.g. a finished job requeued): keep the run's model.pt
        # (a resumed fit would hold the raw weights, not the averaged ones it saved).
        model_path = run_dir / "model.pt"
        done = "kept"
        if trainer.is_global_zero and not model_path.exists():
            from deltar.training.package import package_checkpoint

            package_checkpoint(checkpoint, model_path, float16=False)
            done = "written from its last checkpoint"
        warnings.warn(f"run {run_dir} has finished ({system.schedule_steps} steps); nothing "
                      f"left to train, {model_path} {done}. To train further, start a new run "
                      f"from it (model.init_checkpoint: {model_path})", stacklevel=2)
        return run_dir
    if trainer.is_global_zero and resume:
        # A process killed while saving leaves its partial checkpoint (atomic_path's hidden
        # temporary, as large as a checkpoint); repeated pre-emption would pile them up.
        for partial in leftover_temporaries(run_dir / "checkpoints", ".ckpt"):
            partial.unlink(missing_ok=True)
    if trainer.is_global_zero and not resume:
        held = [p for p in (config_path, run_dir / "model.pt", run_dir / "checkpoints")
                if p.exists()]
        if held:
            if not config_path.exists():
                what = f"{' and '.join(p.name for p in held)} of a run"
            elif checkpoint.is_file():
                what = "a run; resume it"
            else:
                what = ("a run that stopped before its first checkpoint; remove the folder to "
                        "start it again")
            raise FileExistsError(f"run folder {run_dir} already holds {what}, or choose a "
                                  "new folder")
    # Before any training, and before config.yaml makes the folder a run's.
    data.check_val_frames(trainer.global_rank, trainer.world_size,
                          config.trainer.limit_val_batches)
    if trainer.is_global_zero and not resume:
        write_text_atomic(config_path, config.to_yaml(), overwrite=False)
    # Processes that Lightning launches itself (strategy "ddp" without torchrun) inherit
    # the environment and so use the same folder.
    previous = os.environ.get(RUN_DIR_ENV)
    os.environ[RUN_DIR_ENV] = str(run_dir)
    try:
        trainer.fit(system, datamodule=data, ckpt_path=str(checkpoint) if resume else None)
    except SystemExit as stop:
        # Lightning ends a run stopped by SIGTERM with SystemExit(None), which reads as
        # success, and one stopped by Ctrl+C with SystemExit(1): say which, and how to go on.
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        if isinstance(stop, SIGTERMException):
            name = "SIGTERM"
        elif isinstance(stop.__context__, KeyboardInterrupt):  # exit(1) in its handler
            name = "SIGINT"
        else:  # anything else that exits (e.g. a callback's sys.exit) stays as it was
            raise
        raise TrainingInterrupted(run_dir, name, trainer.global_step) from stop
    finally:
        if previous is None:
            os.environ.pop(RUN_DIR_ENV, None)
        else:
            os.environ[RUN_DIR_ENV] = previous
    if trainer.is_global_zero:
        with atomic_path(run_dir / "model.pt") as tmp:
            torch.save(export_model(system.model, config.model.preset), tmp)
    return run_dir


def resumed_run_finished(checkpoint: Path, schedule_steps: int,
                         config: TrainConfig | None = None,
                         system: DeltarSystem | None = None) -> bool:
    """Whether the run saved in ``checkpoint`` has trained all of its ``schedule_steps``.

    Raises:
        ValueError: the checkpoint does not read (the message names the run's other
            checkpoints to resume from), its network is not the one ``system`` (built
            from the configuration) is (:func:`network_mismatch`: which settings and
            tensors differ), its schedule spans another number of steps
            than the configuration now gives, or ``config`` differs from the one it was
            saved with in settings that change what the run learns (a resumed run keeps
            them; :func:`config_changes`).
    """
    try:
        state = read_torch_file(checkpoint, "training checkpoint", weights_only=False)
        step = int(state["global_step"])
        saved_config = state.get(CHECKPOINT_CONFIG_KEY)
        planned = [int(s["total_steps"]) for s in state.get("lr_schedulers", [])
                   if "total_steps" in s]
        mismatch = None if system is None else network_mismatch(state, system)
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        partial = leftover_temporaries(checkpoint.parent, ".ckpt")
        others = sorted(p.name for p in checkpoint.parent.glob("*.ckpt")
                        if p != checkpoint and p not in partial)
        hint = (f"; the run also saved {', '.join(others)}: copy the latest of them over "
                f"{checkpoint.name} to resume from there") if others else ""
        reason = str(err) if isinstance(err, ValueError) else (
            f"{checkpoint}: cannot read training checkpoint: no training state "
            f"({type(err).__name__}: {err})")
        raise ValueError(f"{reason}{hint}") from err
    if mismatch is not None:
        raise ValueError(f"{checkpoint}: its network is not the one "
                         f"{checkpoint.parent.parent / CONFIG_NAME} builds ({mismatch}); "
                         "resume a run from its own checkpoint, with the model settings "
                         "it was started with")
    if planned and planned[0] != schedule_steps:
        raise ValueError(f"{checkpoint}: the run's learning-rate schedule spans {planned[0]} "
                         f"steps, the configuration now gives {schedule_steps} "
                         "(trainer.max_steps, max_epochs, the data or the batch size "
                         "changed); a resumed run keeps its schedule: to train further, "
                         "start a new run from its weights (model.init_checkpoint: "
                         f"{checkpoint})")
    changed = [] if config is None or saved_config is None else config_changes(
        saved_config, config.to_dict())
    if changed:
        shown = ", ".join(changed[:6]) + (f" and {len(changed) - 6} more" if len(changed) > 6
                                          else "")
        raise ValueError(f"{checkpoint.parent.parent / CONFIG_NAME} was edited after the run "
                         f"started ({shown}); a resumed run keeps the settings it was "
                         "started with: undo the edit, or start a new run (with "
                         "model.init_checkpoint for its weights so far)")
    return step >= schedule_steps


def _check_validation_limits(config: TrainConfig, data: DeltarDataModule,
                             trainer: L.Trainer) -> None:
    """The validation settings Lightning refuses only once it trains (``val_check_interval``)
    or first validates (``limit_val_batches``): here, before ``config.yaml`` is written.

    Raises:
        ValueError: ``trainer.val_check_interval`` above the training batches of an epoch,
            or a ``trainer.limit_val_batches`` fraction that is less than one batch.
    """
    tcfg = config.trainer
    if tcfg.limit_val_batches == 0:  # no validation: Lightning checks neither
        return
    batches = train_batches_per_epoch(config, len(data.train_set), trainer.world_size)
    if tcfg.val_check_interval is not None and tcfg.val_check_interval > batches:
        raise ValueError(f"trainer.val_check_interval is {tcfg.val_check_interval} steps but an "
                         f"epoch trains {batches} batches per process: lower it, or set it to "
                         "null to validate at each epoch's end")
    limit = tcfg.limit_val_batches
    if isinstance(limit, float) and data.val_set is not None and len(data.val_set):
        val_batches = len(data.val_dataloader((trainer.global_rank, trainer.world_size)))
        if int(limit * val_batches) == 0:
            raise ValueError(f"trainer.limit_val_batches {limit} of the {val_batches} validation "
                             f"batches per process is less than one batch: raise it to at "
                             f"least {1 / val_batches:.3g}, or give a number of batches")


def train_batches_per_epoch(config: TrainConfig, num_train_items: int, world_size: int) -> int:
    """Training batches each process takes per epoch: ``ceil(items / world_size)`` items in
    full batches, limited by ``limit_train_batches`` (as Lightning limits them)."""
    batches = math.ceil(num_train_items / world_size) // config.data.batch_size
    limit = config.trainer.limit_train_batches
    if isinstance(limit, int):
        batches = min(batches, limit)
    elif isinstance(limit, float):
        batches = int(batches * limit)
    return batches


def count_training_steps(config: TrainConfig, num_train_items: int, world_size: int) -> int:
    """Optimiser steps of the whole run (what the OneCycle schedule spans).

    Matches the data module: each process gets ``ceil(items / world_size)`` items per
    epoch in full batches, limited by ``limit_train_batches``, over ``max_epochs`` epochs,
    capped by ``max_steps``.
    """
    total = train_batches_per_epoch(config, num_train_items, world_size) * \
        config.trainer.max_epochs
    if config.trainer.max_steps > 0:
        total = min(total, config.trainer.max_steps)
    if total < 1:
        raise ValueError(f"the configuration trains for no step ({num_train_items} training "
                         f"frames, batch size {config.data.batch_size}, {world_size} processes)")
    return total


def _default_run_dir(config: TrainConfig) -> Path:
    inherited = os.environ.get(RUN_DIR_ENV)
    if inherited:
        return Path(inherited)
    world = max(int(os.environ.get(name, "1")) for name in ("WORLD_SIZE", "SLURM_NTASKS"))
    if world > 1:
        # Separately started processes (torchrun, srun) would each pick their own timestamp.
        raise ValueError("multi-process launches need an explicit run folder (--run-dir)")
    return new_run_dir(config)
