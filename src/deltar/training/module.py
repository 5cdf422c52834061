"""``DeltarSystem``: the Lightning module that trains a :class:`~deltar.models.DeltarNet`.

The network stays plain PyTorch; this module adds the loss (scaled SI loss on the valid
ground-truth pixels, the prediction upsampled to the ground truth's resolution as the
release does), the optimiser (AdamW, image encoder at a lower learning rate), the
OneCycle schedule and validation with the paper's per-frame metrics.
"""

from __future__ import annotations

import random
import warnings
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from deltar.evaluation.metrics import METRIC_KEYS, EmptyFrameError, depth_metrics
from deltar.io.torch_file import read_torch_file
from deltar.models import DeltarNet, create_model, scaled_si_loss
from deltar.models.checkpoint import (
    CHECKPOINT_FORMAT_VERSION,
    READABLE_FORMAT_VERSIONS,
    checkpoint_payload,
    model_from_config,
)
from deltar.models.config import OUTPUT_STAGE_OPTIONS
from deltar.training.config import OptimConfig

#: Keys of a batch the network consumes.
MODEL_INPUTS: tuple[str, ...] = ("image", "hypotheses", "zone_rects", "zone_valid")


class DeltarSystem(L.LightningModule):
    """Train and validate a DELTAR network.

    Args:
        preset: model preset for :func:`deltar.models.create_model`.
        model_overrides: flat options replacing the preset's
            (:data:`deltar.models.config.FLAT_OPTIONS`).
        optim: loss / optimiser / schedule settings (defaults: the release's recipe).
        min_depth, max_depth: ground-truth range of the validation metrics, metres.
        encoder_weights: pretrained image-encoder weights (see
            :func:`deltar.models.create_model`); None: random.
        allow_download: let timm download ImageNet weights no package ships.

    Attributes:
        schedule_steps: optimiser steps the OneCycle schedule spans. Set it before
            ``fit`` (``deltar.training.run`` does); if None, Lightning's estimate is used,
            which loads the training data early and so defeats mid-epoch resumption.
    """

    def __init__(self, preset: str = "deltar-lite", model_overrides: dict[str, Any] | None = None,
                 optim: OptimConfig | None = None, min_depth: float = 1e-3,
                 max_depth: float = 10.0, encoder_weights: str | None = None,
                 allow_download: bool = False) -> None:
        super().__init__()
        self.preset = preset
        self.model_overrides = dict(model_overrides or {})
        self.optim = optim or OptimConfig()
        self.model = create_model(preset, encoder_weights, allow_download=allow_download,
                                  **self.model_overrides)
        if self.optim.freeze_encoder:
            self.model.image_encoder.requires_grad_(False)
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.schedule_steps: int | None = None
        self._val_sums = torch.zeros(len(METRIC_KEYS), dtype=torch.float64)
        self._val_loss_sum = torch.zeros((), dtype=torch.float64)
        self._val_frames = torch.zeros((), dtype=torch.float64)
        self._val_batches = torch.zeros((), dtype=torch.float64)
        #: Metrics of the last completed validation (averaged over frames and processes).
        self.last_val_metrics: dict[str, float] = {}

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Run the network on a batch dict (see ``deltar.training.data``).

        Returns:
            The network's outputs: ``depth`` (B, 1, H/2, W/2) metres, ``bin_edges``
            (B, N + 1) metres, ``uncertainty`` (B, 1, H/2, W/2) metres.
        """
        # Batches from other readers may lack the no-target flags (then none is known)
        # and the further targets (then each zone reports its primary reading alone).
        return self.model(*(batch[key] for key in MODEL_INPUTS),
                          zone_no_target=batch.get("zone_no_target"),
                          zone_targets=batch.get("zone_targets"))

    def loss(self, pred_m: torch.Tensor, target_m: torch.Tensor) -> torch.Tensor:
        """Scaled SI loss between (B, 1, h, w) predictions and (B, 1, H, W) ground truth.

        The prediction is upsampled bilinearly to the ground truth (as the release does)
        and only pixels with ground truth above ``min_depth`` count.
        """
        valid = target_m > self.min_depth
        # The log in the loss needs float32 even under mixed precision.
        return scaled_si_loss(pred_m.float(), target_m.float(), valid,
                              alpha=self.optim.loss_alpha, lam=self.optim.loss_lambda)

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        """One optimisation step's loss (logged as ``train/loss``)."""
        output = self(batch)
        loss = self.loss(output["depth"], batch["depth"])
        self.log("train/loss", loss, prog_bar=True, batch_size=batch["depth"].shape[0])
        return loss

    # ------------------------------------------------------------------ validation
    def on_validation_epoch_start(self) -> None:
        self._val_sums.zero_()
        self._val_loss_sum.zero_()
        self._val_frames.zero_()
        self._val_batches.zero_()

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        """Accumulate the loss and each frame's metrics at ground-truth resolution."""
        output = self(batch)
        target = batch["depth"]
        self._val_loss_sum += float(self.loss(output["depth"], target))
        self._val_batches += 1
        # Resized as the estimator and `deltar evaluate` do, so training metrics are the
        # metrics users see.
        pred = F.interpolate(output["depth"].float(), size=target.shape[-2:], mode="bilinear",
                             align_corners=False)
        for frame_pred, frame_gt in zip(pred[:, 0].cpu().numpy(), target[:, 0].cpu().numpy(),
                                        strict=True):
            try:
                metrics = depth_metrics(frame_pred, frame_gt, self.min_depth, self.max_depth)
            except EmptyFrameError:
                continue  # no valid ground truth in this frame: it cannot be scored
            self._val_sums += torch.tensor([metrics[k] for k in METRIC_KEYS],
                                           dtype=torch.float64)
            self._val_frames += 1

    def on_validation_epoch_end(self) -> None:
        """Average over frames of all processes, log ``val/<metric>`` and show a table."""
        totals = torch.cat([self._val_sums, self._val_loss_sum[None], self._val_frames[None],
                            self._val_batches[None]]).to(self.device)
        totals = self.trainer.strategy.reduce(totals, reduce_op="sum")
        totals = totals.double().cpu()
        frames, batches = float(totals[-2]), float(totals[-1])
        if frames == 0:
            return
        metrics = {key: float(totals[i]) / frames for i, key in enumerate(METRIC_KEYS)}
        metrics["loss"] = float(totals[len(METRIC_KEYS)]) / max(batches, 1.0)
        self.last_val_metrics = metrics
        for key, value in metrics.items():
            # Already reduced over processes, so no further syncing.
            self.log(f"val/{key}", value, prog_bar=key in ("d1", "rel"), rank_zero_only=True)
        if not self.trainer.sanity_checking and self.trainer.is_global_zero:
            print_metrics_table(metrics, int(frames), self.current_epoch, self.global_step)

    # ------------------------------------------------------------------ optimisation
    def train(self, mode: bool = True) -> DeltarSystem:
        """Train mode, except a frozen encoder, whose batch norms keep their statistics."""
        super().train(mode)
        if self.optim.freeze_encoder:
            self.model.image_encoder.eval()
        return self

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        # Lightning sets each submodule's mode itself (at the start of fit and after
        # each validation), bypassing train(): a frozen encoder is put back in eval mode
        # before every step, or its batch norms would follow the training batches.
        if self.optim.freeze_encoder:
            self.model.image_encoder.eval()

    def parameter_groups(self) -> list[dict[str, Any]]:
        """AdamW groups: the image encoder at ``lr * encoder_lr_factor`` (none when frozen),
        the rest at lr."""
        encoder = list(self.model.image_encoder.parameters())
        encoder_ids = {id(p) for p in encoder}
        rest = [p for p in self.model.parameters() if id(p) not in encoder_ids]
        groups = [{"params": rest, "lr": self.optim.lr, "name": "decoder"}]
        if not self.optim.freeze_encoder:
            groups.insert(0, {"params": encoder,
                              "lr": self.optim.lr * self.optim.encoder_lr_factor,
                              "name": "encoder"})
        return groups

    def configure_optimizers(self) -> dict[str, Any]:
        """AdamW + OneCycle, stepped every optimiser step over the whole run."""
        cfg = self.optim
        groups = self.parameter_groups()
        optimizer = torch.optim.AdamW(groups, lr=cfg.lr, betas=tuple(cfg.betas),
                                      weight_decay=cfg.weight_decay)
        scheduler = torch.optim.lr_scheduler.OneCycleLR(
            optimizer, max_lr=[g["lr"] for g in groups],
            total_steps=self.schedule_steps or int(self.trainer.estimated_stepping_batches),
            pct_start=cfg.pct_start, div_factor=cfg.div_factor,
            final_div_factor=cfg.final_div_factor, cycle_momentum=cfg.cycle_momentum,
            base_momentum=cfg.base_momentum, max_momentum=cfg.max_momentum)
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Store the model recipe and this process's RNG states next to the weights."""
        # The full network config, so the checkpoint survives changes to preset defaults.
        checkpoint["deltar_model"] = {"preset": self.preset, "config": self.model.config(),
                                      "format_version": CHECKPOINT_FORMAT_VERSION}
        # The legacy global numpy state is what third-party code (and timm) draws from.
        checkpoint["deltar_rng"] = {
            "torch": torch.get_rng_state(), "numpy": np.random.get_state(),  # noqa: NPY002
            "python": random.getstate(),
        }
        if torch.cuda.is_available():
            checkpoint["deltar_rng"]["cuda"] = torch.cuda.get_rng_state_all()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Restore the RNG states saved by :meth:`on_save_checkpoint` (resuming)."""
        states = checkpoint.get("deltar_rng")
        if states:
            torch.set_rng_state(states["torch"])
            np.random.set_state(states["numpy"])  # noqa: NPY002
            random.setstate(states["python"])
            if "cuda" in states and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(states["cuda"])


def print_metrics_table(metrics: dict[str, float], frames: int, epoch: int, step: int) -> None:
    """Print validation metrics as a rich table (d1..d3 higher is better, others lower)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"validation: epoch {epoch}, step {step}, {frames} frames")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("better", justify="center")
    for key in [*METRIC_KEYS, "loss"]:
        table.add_row(key, f"{metrics[key]:.4f}", "higher" if key in ("d1", "d2", "d3")
                      else "lower")
    Console().print(table)


def export_model(model: nn.Module, preset: str) -> dict[str, Any]:
    """The dict ``deltar train`` saves as ``model.pt``: a deltar checkpoint
    (:func:`deltar.models.checkpoint.checkpoint_payload`) with the network's full config,
    so later changes to a preset's defaults cannot change the saved architecture."""
    return checkpoint_payload(model, preset)


def load_trained_model(path: str, map_location: str = "cpu") -> nn.Module:
    """Rebuild a trained network from a ``model.pt`` export or a Lightning checkpoint.

    Args:
        path: ``model.pt`` written by ``deltar train`` or a run's ``.ckpt`` file.
        map_location: torch device for the loaded tensors.

    Returns:
        The :class:`~deltar.models.DeltarNet` with the trained weights, in eval mode.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is neither kind.
    """
    model, _ = _load_weights_file(path, map_location)
    return model.eval()


def _load_weights_file(path: str, map_location: str = "cpu",
                       model_config: dict[str, Any] | None = None,
                       ) -> tuple[nn.Module, dict[str, Any]]:
    data = read_torch_file(path, "weights file", weights_only=False,
                           map_location=map_location)
    if isinstance(data, dict) and "deltar_model" in data and "state_dict" in data:
        recipe = dict(data["deltar_model"])
        prefix = "model."
        state = {k[len(prefix):]: v for k, v in data["state_dict"].items()
                 if k.startswith(prefix)}
        version = recipe.get("format_version")
        # Format 2 stored the flat options as "overrides".
        config = recipe.get("config", recipe.get("overrides"))
    elif isinstance(data, dict) and {"preset", "config", "state_dict"} <= set(data):
        recipe = {"preset": data["preset"], "config": data["config"]}
        state, version, config = data["state_dict"], data.get("format_version"), data["config"]
    else:
        raise ValueError(f"{path} is neither a deltar training checkpoint nor a model.pt "
                         "export")
    if version not in READABLE_FORMAT_VERSIONS:
        raise ValueError(f"{path}: unsupported checkpoint format_version {version!r} (this "
                         f"deltar reads versions {READABLE_FORMAT_VERSIONS})")
    model = model_from_config(recipe["preset"], dict(config), version, model_config)
    model.load_state_dict(state)
    return model, recipe


def initial_weights(model: DeltarNet, path: str, preset: str | None = None) -> None:
    """Load a previous run's weights (``.ckpt`` or ``model.pt``, or a bundled model's
    name such as ``"default"``) into ``model`` (fine-tuning).

    Only the weights are taken: the configured model's input contract stays, and a
    ``UserWarning`` names each input setting it changes from the weights' (e.g.
    ``design_size``, ``histogram_hypotheses``) and says when the weights carry a fitted
    output stage (blend, sigma, ...), which a new run does not keep: it is fitted again
    on the new model (``deltar fit-uncertainty``).

    Args:
        model: the configured network.
        path: the weights file or bundled name.
        preset: the configured preset, named when the weights are of another one.

    Raises:
        ValueError: the architectures differ (the message lists mismatching keys, or
            names both presets when they differ).
    """
    from deltar.weights import resolve_checkpoint

    source, recipe = _load_weights_file(str(resolve_checkpoint(path)))
    if preset is not None and recipe["preset"] != preset:
        raise ValueError(f"{path} holds a {recipe['preset']} network; the configuration "
                         f"builds a {preset} (model.preset)")
    try:
        model.load_state_dict(source.state_dict())
    except RuntimeError as err:
        lines = str(err).splitlines()
        raise ValueError(f"weights in {path} do not fit the configured model: "
                         f"{' '.join(lines[:3])[:600]}") from err
    was, now = source.network_config.inputs, model.network_config.inputs
    changed = [f"{name} {_setting(getattr(was, name))} -> {_setting(getattr(now, name))}"
               for name in was.__dataclass_fields__ if getattr(was, name) != getattr(now, name)]
    if changed:
        warnings.warn(f"{path}: this run changes the weights' input settings: "
                      f"{'; '.join(changed)} (set model.overrides to keep them)",
                      UserWarning, stacklevel=2)
    fitted = [name for name in OUTPUT_STAGE_OPTIONS
              if getattr(source.network_config.output, name) is not None
              and getattr(source.network_config.output, name)
              != getattr(model.network_config.output, name)]
    if fitted:
        warnings.warn(f"{path} carries a fitted output stage ({', '.join(fitted)}); the new "
                      "run's model.pt has none: fit it on the new model (deltar "
                      "fit-uncertainty)", UserWarning, stacklevel=2)


def _setting(value: Any) -> str:
    """A setting as a config file writes it (lower-case booleans, lists for tuples)."""
    if isinstance(value, bool):
        return str(value).lower()
    return str(list(value)) if isinstance(value, tuple) else str(value)
