"""How Lightning writes a run folder: checkpoints saved atomically and read back from
a folder that may have moved, the CSV log a resumed run appends to, the configuration
kept in every checkpoint (so a resume can tell an edited ``config.yaml``) and the
per-step training history. :mod:`deltar.training.run` assembles them.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO

from deltar.io.atomic import atomic_path, write_text_atomic
from deltar.io.input_file import input_file
from deltar.training.config import TrainConfig


class AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoint files written through :func:`deltar.io.atomic.atomic_path`.

    The checkpoint is serialised into a temporary file in the same folder and renamed
    over the target only when complete, so a process killed while saving never leaves
    a truncated ``last.ckpt``. Loading allows the non-tensor objects our checkpoints
    hold (RNG states), so only load checkpoints you wrote yourself.
    """

    def save_checkpoint(self, checkpoint: dict[str, Any], path: str | os.PathLike,
                        storage_options: Any | None = None) -> None:
        """Serialise ``checkpoint`` to ``path`` atomically."""
        if storage_options is not None:
            raise TypeError("AtomicCheckpointIO takes no storage_options")
        with atomic_path(path) as tmp:
            torch.save(checkpoint, tmp)

    def load_checkpoint(self, path: str | os.PathLike, map_location: Any = None,
                        weights_only: bool | None = None) -> dict[str, Any]:
        """Load a checkpoint written by this project (full pickle, trusted source)."""
        input_file(path, "checkpoint")
        return torch.load(path, map_location=map_location or "cpu", weights_only=False)


class RunCheckpoints(ModelCheckpoint):
    """Lightning's checkpoint callback for a run folder that may have moved.

    Its saved state names files by absolute path; Lightning drops that state when the
    folder differs, then versions ``last.ckpt`` (``last-v1.ckpt``: a later resume reads the
    stale one) and stops pruning ``step=*.ckpt``. The paths are read here as the same
    files in the run's current ``checkpoints/`` folder, so a moved or copied run resumes
    like one that stayed.
    """

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore the state, its paths moved to this run's checkpoints folder."""
        saved = state_dict.get("dirpath")
        if saved and self.dirpath and saved != self.dirpath:
            def here(path: Any) -> Any:
                moved = isinstance(path, str) and path and os.path.dirname(path) == saved
                return os.path.join(self.dirpath, os.path.basename(path)) if moved else path

            state_dict = {**state_dict, "dirpath": self.dirpath,
                          "best_k_models": {here(path): score for path, score in
                                            state_dict.get("best_k_models", {}).items()},
                          **{key: here(state_dict[key]) for key in
                             ("best_model_path", "kth_best_model_path", "last_model_path")
                             if key in state_dict}}
        super().load_state_dict(state_dict)


def appending_csv_logger(save_dir: Path, version: str) -> Any:
    """Lightning's CSV logger writing ``<save_dir>/<version>/metrics.csv``, appending to
    the file a resumed run finds there (Lightning's own deletes it).

    Steps re-done after the last checkpoint appear twice; the later rows are the run's.
    """
    import csv

    from lightning.pytorch.loggers import CSVLogger
    from lightning.pytorch.loggers.csv_logs import ExperimentWriter

    class AppendingWriter(ExperimentWriter):
        def _check_log_dir_exists(self) -> None:
            # The existing header's columns (Lightning writes them sorted), so new rows
            # line up with the old ones; a new column rewrites the file with it.
            if self._fs.isfile(self.metrics_file_path):
                with self._fs.open(self.metrics_file_path, "r", newline="") as file:
                    self.metrics_keys = next(csv.reader(file), [])

    class AppendingCSVLogger(CSVLogger):
        @property
        def experiment(self) -> ExperimentWriter:
            if self._experiment is None:
                self._fs.makedirs(self.root_dir, exist_ok=True)
                self._experiment = AppendingWriter(log_dir=self.log_dir)
            return self._experiment

    return AppendingCSVLogger(save_dir, name="", version=version)


#: Where a checkpoint holds the run's configuration (:class:`RunConfigRecord`).
CHECKPOINT_CONFIG_KEY = "deltar_train_config"
#: Settings a resumed run may change (dotted, ``*`` for a list entry): where the files
#: are and how the run is shown, checkpointed or spread over devices; not what it learns.
RESUMABLE_CHANGES = ("name", "output_dir", "data.num_workers", "data.val_batch_size",
                     "data.sources.*.path", "data.sources.*.data_root",
                     "model.init_checkpoint", "model.official_weights",
                     "model.encoder_weights",  # a resume reads every weight from its ckpt
                     "trainer.progress_bar", "trainer.num_threads", "trainer.log_every_n_steps",
                     "trainer.checkpoint_every_n_steps", "trainer.keep_checkpoints",
                     "trainer.accelerator", "trainer.strategy", "trainer.val_every_n_epochs",
                     "trainer.val_check_interval", "trainer.limit_val_batches")
# Not trainer.devices or num_nodes: the batch each step takes is batch_size x processes.


class RunConfigRecord(Callback):
    """Stores the run's configuration in every checkpoint, so that a resume can tell a
    ``config.yaml`` edited since (:func:`config_changes`)."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config.to_dict()

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           checkpoint: dict[str, Any]) -> None:
        checkpoint[CHECKPOINT_CONFIG_KEY] = self.config


def config_changes(saved: dict[str, Any], config: dict[str, Any]) -> list[str]:
    """The dotted settings (``optim.lr``, ``data.sources.0.frames``) whose values differ
    between two configuration dicts, except :data:`RESUMABLE_CHANGES`."""
    from fnmatch import fnmatchcase

    before, after = _flat_settings(saved), _flat_settings(config)
    return sorted(key for key in before.keys() | after.keys()
                  if before.get(key) != after.get(key) and not any(
                      fnmatchcase(key, pattern) for pattern in RESUMABLE_CHANGES))


def _flat_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """A nested settings dict as ``{dotted key: value}`` (list entries that are dicts by
    index: ``data.sources.0.frames``), values as the YAML file holds them (a config
    built in code may hold tuples)."""

    def flat(value: Any, prefix: str) -> dict[str, Any]:
        if isinstance(value, dict):
            items = value.items()
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            items = ((str(i), v) for i, v in enumerate(value))
        else:
            return {prefix.rstrip("."): value}
        return {k: v for key, item in items for k, v in flat(item, f"{prefix}{key}.").items()}

    return flat(json.loads(json.dumps(settings)), "")


def network_mismatch(checkpoint: dict[str, Any], system: torch.nn.Module) -> str | None:
    """What differs between the network a training checkpoint holds and ``system`` (the
    one the configuration builds), or None when the checkpoint's weights load into it.

    Loads the weights into ``system`` to find out (with the model's own load hooks, so
    tensors a model skips on loading are not counted): a resume loads the same ones.

    Args:
        checkpoint: the Lightning checkpoint dict (``state_dict``, ``deltar_model``).
        system: the :class:`~deltar.training.module.DeltarSystem` to resume into.

    Returns:
        e.g. ``"head_channels 8 in the checkpoint, 16 configured; 3 tensor(s) of other
        shapes (model.head.conv.weight: [8, 8, 1, 1] in the checkpoint, [16, 16, 1, 1]
        configured, ...)"``, also naming missing and unexpected tensors.
    """
    state = checkpoint["state_dict"]
    own = system.state_dict()
    wrong = [f"{key}: {list(value.shape)} in the checkpoint, {list(own[key].shape)} "
             "configured" for key, value in state.items()
             if key in own and tuple(value.shape) != tuple(own[key].shape)]
    if wrong:
        problems = [f"{len(wrong)} tensor(s) of other shapes ({'; '.join(wrong[:2])}"
                    f"{'; ...' if len(wrong) > 2 else ''})"]
    else:  # every shape fits: the load itself names what is missing or unexpected
        result = system.load_state_dict(state, strict=False)
        problems = [f"{len(keys)} tensor(s) {kind} ({', '.join(keys[:3])}"
                    f"{', ...' if len(keys) > 3 else ''})"
                    for kind, keys in (("missing from the checkpoint", result.missing_keys),
                                       ("unexpected", result.unexpected_keys)) if keys]
    if not problems:
        return None
    # Why, where the checkpoint says how its network was built.
    saved = checkpoint.get("deltar_model") or {}
    model = getattr(system, "model", None)
    settings = []
    if saved.get("preset") not in (None, getattr(system, "preset", None)):
        settings.append(f"preset {saved['preset']} in the checkpoint, "
                        f"{getattr(system, 'preset', None)} configured")
    if isinstance(saved.get("config"), dict) and callable(getattr(model, "config", None)):
        before, now = _flat_settings(saved["config"]), _flat_settings(model.config())
        settings += [f"{key} {before.get(key)} in the checkpoint, {now.get(key)} configured"
                     for key in sorted(before.keys() | now.keys())
                     if before.get(key) != now.get(key)]
    return "; ".join(settings + problems)


class TrainingHistory(Callback):
    """Append each step's loss and sample indices to ``history/rank<r>.jsonl``.

    One file per process, one JSON line per optimiser step:
    ``{"step", "epoch", "loss", "indices", "time"}`` (time: Unix seconds at the step's
    end). A resumed run appends to the same file, so steps re-done after the last
    checkpoint appear twice (the later line wins). At the end of training each process
    writes ``history/rank<r>_final.json`` with the global step and a SHA-256 digest of
    its parameters (equal on all ranks under DDP).
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def _path(self, trainer: L.Trainer, suffix: str) -> Path:
        return self.folder / f"rank{trainer.global_rank}{suffix}"

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           outputs: Any, batch: dict[str, torch.Tensor], batch_idx: int
                           ) -> None:
        loss = outputs["loss"] if isinstance(outputs, dict) else outputs
        record = {"step": trainer.global_step, "epoch": trainer.current_epoch,
                  "loss": float(loss), "indices": batch["index"].tolist(),
                  "time": round(time.time(), 3)}
        self.folder.mkdir(parents=True, exist_ok=True)
        with self._path(trainer, ".jsonl").open("a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        digest = parameter_digest(pl_module)
        write_text_atomic(self._path(trainer, "_final.json"), json.dumps(
            {"step": trainer.global_step, "parameters_sha256": digest}) + "\n")


def parameter_digest(module: torch.nn.Module) -> str:
    """SHA-256 over the bytes of every parameter (names and values), in order."""
    sha = hashlib.sha256()
    for name, param in module.named_parameters():
        sha.update(name.encode())
        sha.update(param.detach().cpu().contiguous().numpy().tobytes())
    return sha.hexdigest()


def read_history(path: str | Path) -> dict[int, dict[str, Any]]:
    """Read a ``history/rank<r>.jsonl`` file: step -> record (the last record per step)."""
    records: dict[int, dict[str, Any]] = {}
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        if line.strip():
            record = json.loads(line)
            records[int(record["step"])] = record
    return records
