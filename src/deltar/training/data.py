"""Training data: datasets from a :class:`DataConfig`, hold-out splits, resumable loading.

Every item is a dict of tensors with the keys of
:class:`deltar.training.datasets.SimulatedL5Dataset` plus ``index`` (the item's position in
the concatenated dataset, recorded so that data sharding can be audited).

Loading is deterministic and resumable: :class:`ShardedSampler` draws the order of epoch
``e`` from ``(seed, e)`` and gives each process its own shard, and
:class:`ResumableDataLoader` remembers how many batches of the epoch it has handed out,
so Lightning can store that in a checkpoint and a resumed run skips exactly those.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from deltar.camera import CameraIntrinsics
from deltar.data.rgbd import RGBDFrame
from deltar.data.transforms import ImageAugmentation
from deltar.data.zone_sets import open_zone_set
from deltar.models.config import InputConfig
from deltar.sensor.augment import SignalAugmentation
from deltar.training.config import ZONE_SET_SOURCE_KINDS, DataConfig, SourceConfig
from deltar.training.config_checks import check_frames_fit
from deltar.training.datasets import IndexedConcat, SimulatedL5Dataset, ZJUL5TrainingDataset


# ---------------------------------------------------------------------- readers
class ResizedReader(Sequence):
    """View of an RGB-D reader with every frame resized (image: area, depth: nearest).

    Args:
        reader: sequence of :class:`~deltar.data.rgbd.RGBDFrame`.
        height, width: output size in pixels.
    """

    def __init__(self, reader: Sequence[RGBDFrame], height: int, width: int) -> None:
        if height < 1 or width < 1:
            raise ValueError(f"resize height and width must be >= 1, got {height}x{width}")
        self.reader, self.height, self.width = reader, int(height), int(width)

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int) -> RGBDFrame:  # type: ignore[override]
        frame = self.reader[index]
        size = (self.width, self.height)
        # Nearest neighbour for depth: averaging across an edge invents surfaces.
        return RGBDFrame(
            image=cv2.resize(frame.image, size, interpolation=cv2.INTER_AREA),
            depth_m=cv2.resize(frame.depth_m, size, interpolation=cv2.INTER_NEAREST),
            intrinsics=frame.intrinsics.scaled(self.height, self.width),
            name=frame.name, timestamp_s=frame.timestamp_s)


class SubsetReader(Sequence):
    """The frames ``indices`` of a reader (or of any sequence), in that order."""

    def __init__(self, reader: Sequence, indices: Sequence[int]) -> None:
        self.reader, self.indices = reader, [int(i) for i in indices]

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> Any:
        return self.reader[self.indices[index]]


def holdout_split(num_frames: int, fraction: float, position: str = "end", where: str = ""
                  ) -> tuple[list[int], list[int]]:
    """Split ``range(num_frames)`` into training frames and one contiguous held-out block.

    Args:
        num_frames: frames in the sequence.
        fraction: share of frames held out, in (0, 1); at least one frame is held out
            and at least one trains.
        position: ``end`` (the last frames) or ``start`` (the first frames).
        where: what the frames are (e.g. ``data.sources.0 (path)``), for the message.

    Returns:
        ``(train_indices, val_indices)``.

    Raises:
        ValueError: fewer than two frames, a fraction outside (0, 1) or a bad position.
    """
    if num_frames < 2:
        raise ValueError(f"{where + ': ' if where else ''}need at least 2 frames to hold "
                         f"some out, got {num_frames}")
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"holdout fraction must be in (0, 1), got {fraction}")
    held = min(max(round(num_frames * fraction), 1), num_frames - 1)
    frames = list(range(num_frames))
    if position == "end":
        return frames[:num_frames - held], frames[num_frames - held:]
    if position == "start":
        return frames[held:], frames[:held]
    raise ValueError(f"holdout position must be 'end' or 'start', got {position!r}")


def open_source_reader(source: SourceConfig) -> Sequence:
    """Open one source's frames: RGB-D frames, or samples for ``zju_l5`` / ``thdr3k``."""
    from deltar.data.nyu import NYU_INTRINSICS, NYUH5Reader, NYULabeledReader
    from deltar.data.procedural import ProceduralReader
    from deltar.data.rgbd import open_rgbd

    if source.kind in ZONE_SET_SOURCE_KINDS:
        return open_zone_set(source.path, split=source.split, kind=source.kind)
    if source.kind == "procedural":
        height, width = source.resize or (480, 640)
        # Rendered directly at the requested size: exact depth, no resampling.
        return ProceduralReader(source.frames, source.seed, height, width)
    intrinsics = None
    if source.intrinsics is not None:
        height, width = _native_size(source)
        intrinsics = CameraIntrinsics(*source.intrinsics, width=width, height=height)
    if source.kind == "rgbd":
        reader = open_rgbd(source.path, depth_scale=source.depth_scale, intrinsics=intrinsics)
    elif str(source.path).lower().endswith(".mat"):
        reader = NYULabeledReader(source.path, intrinsics=intrinsics or NYU_INTRINSICS)
    else:
        reader = NYUH5Reader(source.path, split=source.split, data_root=source.data_root,
                             intrinsics=intrinsics or NYU_INTRINSICS,
                             crop_border=source.crop_border)
    if source.resize is not None:
        reader = ResizedReader(reader, *source.resize)
    return reader


#: The median depth (metres) a scene to train on must read: outside it the depth's units
#: are wrong (a depth image in metres read as millimetres reads 0-10 mm).
PLAUSIBLE_MEDIAN_DEPTH_M = (0.05, 100.0)


def check_depth_units(depths_m: Sequence[np.ndarray], where: str) -> None:
    """Refuse frames whose valid depth (> 0, metres) has a median outside
    :data:`PLAUSIBLE_MEDIAN_DEPTH_M`, or that have none: their units are wrong, and
    training on them would finish without a word (the zones simulated from them read
    nothing).

    Args:
        depths_m: a few (H, W) depth maps of a source (e.g. spread through it), metres
            as it reads them.
        where: the source, for the message.
    """
    valid = np.concatenate([np.asarray(d)[np.asarray(d) > 0].reshape(-1)[::16]
                            for d in depths_m])
    low, high = PLAUSIBLE_MEDIAN_DEPTH_M
    if valid.size == 0:
        raise ValueError(f"{where}: the {len(depths_m)} frames read to check it have no depth "
                         "(every pixel 0); check the depth files and depth_scale")
    median = float(np.median(valid))
    if not low <= median <= high:
        raise ValueError(f"{where}: its depth reads a median of {median:.4g} m, outside "
                         f"{low:g}-{high:g} m for a scene to train on: its units are likely "
                         "wrong; set depth_scale to the depth files' units per metre (1000 "
                         "for millimetres, 5000 for TUM's, 1 for files in metres)")


def _native_size(source: SourceConfig) -> tuple[int, int]:
    """(height, width) of a source's stored frames, read from its first frame."""
    from deltar.data.nyu import NYUH5Reader, NYULabeledReader
    from deltar.data.rgbd import open_rgbd

    if source.kind == "rgbd":
        # Intrinsics are not needed to learn the size; silence the default-camera warning.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reader = open_rgbd(source.path, depth_scale=source.depth_scale)
    elif str(source.path).lower().endswith(".mat"):
        reader = NYULabeledReader(source.path)
    else:
        reader = NYUH5Reader(source.path, split=source.split, data_root=source.data_root)
    return tuple(reader[0].depth_m.shape)


# ---------------------------------------------------------------------- datasets
def build_datasets(config: DataConfig, seed: int = 0, inputs: InputConfig | None = None
                   ) -> tuple[IndexedConcat, IndexedConcat]:
    """Training and validation datasets described by a data config.

    Each ``train_val`` source is split into training frames and one contiguous held-out
    block (:func:`holdout_split`); ``train`` / ``val`` sources go entirely to one side.
    Training items are augmented (image and signal, as configured); validation items
    are not.

    Args:
        config: the data section of a training config.
        seed: base seed of all item randomness.
        inputs: the network's input contract (``model.network_config.inputs``): its
            ``image_mean`` / ``image_std`` normalise the images, and with
            ``histogram_hypotheses`` the hypotheses of zone sets that carry histograms
            are drawn from them. None: ``InputConfig()`` (ImageNet's normalisation,
            hypotheses from each zone's mean and sigma).

    Returns:
        ``(train, val)`` datasets of item dicts (see the module docstring).

    Raises:
        FileNotFoundError: a source path does not exist.
        ValueError: a source is empty or too small to split.
    """
    inputs = InputConfig() if inputs is None else inputs
    image_mean, image_std = inputs.image_mean, inputs.image_std
    image_aug = None
    if config.image_augmentation.enabled:
        aug = config.image_augmentation
        image_aug = ImageAugmentation(
            crop_size=tuple(aug.crop) if aug.crop else None,
            max_rotation_deg=aug.max_rotation_deg, flip_prob=aug.flip_prob,
            photometric_prob=aug.photometric_prob, max_zoom=aug.max_zoom)
    signal_aug = None
    if config.signal_augmentation.enabled:
        sig = config.signal_augmentation
        signal_aug = SignalAugmentation(sig.drop_fraction, sig.noise_prob, sig.noise_mean_m,
                                        sig.noise_std_m)

    def simulated(reader: Sequence, train: bool, source_seed: int) -> Dataset:
        layout = config.zone_layout if train else (config.val_zone_layout
                                                   or config.zone_layout)
        return SimulatedL5Dataset(
            reader, zone_layout=layout, grid=config.grid,
            training_grid=config.training_grid, training_zone_px=config.training_zone_px,
            training_max_offset_px=config.training_max_offset_px if train else 0,
            signal_augmentation=signal_aug if train else None,
            image_augmentation=image_aug if train else None,
            num_hypotheses=config.num_hypotheses, sampling=config.sampling,
            seed=source_seed,
            depth_scale_range=(tuple(config.depth_scale_range)
                               if train and config.depth_scale_range else None),
            layout_jitter_px=config.layout_jitter_px if train else 0.0,
            layout_rotation_deg=config.layout_rotation_deg if train else 0.0,
            image_mean=image_mean, image_std=image_std, max_targets=config.max_targets)

    train_parts: list[Dataset] = []
    val_parts: list[Dataset] = []
    for number, source in enumerate(config.sources):
        try:
            reader = open_source_reader(source)
        except FileNotFoundError as err:
            # A config copied elsewhere: relative paths are read from the working folder.
            where = "" if source.path is None or Path(source.path).is_absolute() else \
                f" (a relative path, read from the working folder {Path.cwd()})"
            raise FileNotFoundError(f"data.sources.{number}.path: {err}{where}") from err
        if source.every > 1:
            reader = SubsetReader(reader, range(0, len(reader), source.every))
        if len(reader) == 0:
            raise ValueError(f"data.sources.{number} ({source.label()}) has no frames")
        if source.kind not in ZONE_SET_SOURCE_KINDS:
            first = reader[0].depth_m
            if source.kind != "procedural":
                # A few frames spread through the source (its first may be blank).
                picks = np.unique(np.linspace(0, len(reader) - 1, min(5, len(reader)))
                                  .round().astype(int))
                check_depth_units([first, *(reader[int(i)].depth_m for i in picks[1:])],
                                  f"data.sources.{number} ({source.label()})")
            check_frames_fit(config, first.shape[:2], number, source)
            crop = config.image_augmentation.crop if config.image_augmentation.enabled else None
            # Only a source whose every frame trains is cropped to the network's sides.
            cropped = source.role == "train" and crop is not None
            if not cropped and (first.shape[0] % 32 or first.shape[1] % 32):
                # Found here, not at the first batch of an epoch's validation.
                near = [max(32, 32 * round(side / 32)) for side in first.shape[:2]]
                raise ValueError(f"data.sources.{number} ({source.label()}): frames are "
                                 f"{first.shape[0]}x{first.shape[1]}, the network takes "
                                 "sides divisible by 32: set data.sources."
                                 f"{number}.resize (e.g. {near})")
        if source.role == "train_val":
            train_idx, val_idx = holdout_split(len(reader), source.holdout_fraction,
                                               source.holdout_position,
                                               f"data.sources.{number} ({source.label()})")
        elif source.role == "train":
            train_idx, val_idx = list(range(len(reader))), []
        else:
            train_idx, val_idx = [], list(range(len(reader)))
        source_seed = seed * 1000 + number
        for indices, train, parts in ((train_idx, True, train_parts),
                                      (val_idx, False, val_parts)):
            if not indices:
                continue
            subset = SubsetReader(reader, indices)
            if source.kind in ZONE_SET_SOURCE_KINDS:
                flip = config.image_augmentation.flip_prob if (
                    train and config.image_augmentation.enabled) else 0.0
                parts.append(ZJUL5TrainingDataset(subset, config.num_hypotheses,
                                                  config.sampling, flip, source_seed,
                                                  image_mean, image_std,
                                                  with_targets=config.max_targets > 1,
                                                  from_histograms=inputs.histogram_hypotheses))
            else:
                parts.append(simulated(subset, train, source_seed))
    return IndexedConcat(train_parts), IndexedConcat(val_parts)


# ---------------------------------------------------------------------- loading
class ShardedSampler(Sampler[int]):
    """Deterministic per-epoch order, split into one shard per process.

    The order of epoch ``e`` is a permutation drawn from ``(seed, e)`` (or the identity
    when not shuffling). With ``pad=True`` the order is padded by wrapping around so
    that every rank gets the same number of items (needed for DDP training, where all
    ranks must take the same number of steps); validation uses ``pad=False`` so no
    frame is counted twice. Rank ``r`` takes items ``r, r + world, r + 2 world, ...``.

    Args:
        num_items: dataset length.
        shuffle: permute per epoch.
        seed: base seed of the permutations.
        rank, world_size: this process and the number of processes.
        pad: equalise shard sizes by repeating items.
    """

    def __init__(self, num_items: int, shuffle: bool = True, seed: int = 0, rank: int = 0,
                 world_size: int = 1, pad: bool = True) -> None:
        if num_items < 1:
            raise ValueError("ShardedSampler needs at least one item")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank must be in [0, {world_size}), got {rank}")
        self.num_items, self.shuffle, self.seed = num_items, shuffle, int(seed)
        self.rank, self.world_size, self.pad = rank, world_size, pad
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch (called by Lightning before each epoch)."""
        self.epoch = int(epoch)

    def indices(self) -> list[int]:
        """This rank's items for the current epoch, in order."""
        if self.shuffle:
            order = np.random.default_rng((self.seed, self.epoch)).permutation(self.num_items)
        else:
            order = np.arange(self.num_items)
        if self.pad:
            total = math.ceil(self.num_items / self.world_size) * self.world_size
            order = np.resize(order, total)  # wraps around
        return order[self.rank::self.world_size].tolist()

    def __iter__(self) -> Iterator[int]:
        return iter(self.indices())

    def __len__(self) -> int:
        if self.pad:
            return math.ceil(self.num_items / self.world_size)
        return len(range(self.rank, self.num_items, self.world_size))


def collate_frames(items: list[dict[str, Any]]) -> dict[str, Any]:
    """PyTorch's default collation of item dicts, refusing frames of several sizes in
    one batch with what to set (it would fail deep in the loader, at the first step).

    Raises:
        ValueError: items whose tensors differ in shape, naming the shapes and the fix.
    """
    from torch.utils.data import default_collate

    try:
        return default_collate(items)
    except RuntimeError as err:
        if "equal size" not in str(err):
            raise
        sizes = sorted({tuple(item["image"].shape[-2:]) for item in items if "image" in item})
        if len(sizes) > 1:
            raise ValueError(f"one batch holds frames of several sizes ({sizes}, height x "
                             "width): give every source the same data.sources.N.resize, or "
                             "crop them alike (data.image_augmentation.crop)") from err
        differ = sorted(key for key in items[0] if torch.is_tensor(items[0][key]) and len(
            {tuple(item[key].shape) for item in items if torch.is_tensor(item.get(key))}) > 1)
        raise ValueError(f"one batch holds items whose {', '.join(differ)} differ in shape "
                         "(e.g. sources with different zone grids: a zone set's own and the "
                         "simulated data.training_grid)") from err


class ResumableDataLoader(DataLoader):
    """A DataLoader that can resume in the middle of an epoch.

    ``state_dict()`` records the sampler's epoch and how many batches this epoch has
    been handed out; after ``load_state_dict()``, the next iteration over that epoch
    starts after those batches (without loading them). Lightning saves and restores
    this state with its checkpoints (its ``_Stateful`` protocol). Needs a
    :class:`ShardedSampler` and batches of a fixed size (``drop_last`` or a final
    partial batch only at the very end).
    """

    def __init__(self, dataset: Dataset, sampler: ShardedSampler, **kwargs: Any) -> None:
        super().__init__(dataset, sampler=sampler, **kwargs)
        self._served = 0
        self._resume: tuple[int, int] | None = None

    def __iter__(self) -> Iterator[Any]:
        sampler: ShardedSampler = self.sampler  # type: ignore[assignment]
        if hasattr(self.dataset, "set_epoch"):
            # Workers are created per iteration (not persistent), so they copy this epoch.
            self.dataset.set_epoch(sampler.epoch)
        skip = 0
        if self._resume is not None and self._resume[0] == sampler.epoch:
            skip = self._resume[1]
        self._resume = None
        self._served = skip
        if skip == 0:
            yield from self._counted(super().__iter__())
            return
        # Serve the rest of the epoch from a loader over the remaining items only.
        remaining = sampler.indices()[skip * self.batch_size:]
        rest = DataLoader(self.dataset, batch_size=self.batch_size, sampler=remaining,
                          num_workers=self.num_workers, collate_fn=self.collate_fn,
                          pin_memory=self.pin_memory, drop_last=self.drop_last,
                          worker_init_fn=self.worker_init_fn)
        yield from self._counted(iter(rest))

    def _counted(self, batches: Iterator[Any]) -> Iterator[Any]:
        for batch in batches:
            self._served += 1
            yield batch

    def state_dict(self) -> dict[str, int]:
        """``{"epoch", "batches"}``: position in the current epoch."""
        return {"epoch": self.sampler.epoch, "batches": self._served}  # type: ignore[attr-defined]

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Resume after ``state["batches"]`` batches of epoch ``state["epoch"]``."""
        self._resume = (int(state["epoch"]), int(state["batches"]))


class DeltarDataModule(L.LightningDataModule):
    """Lightning data module built from the ``data`` section of a training config.

    Args:
        config: data configuration.
        seed: base seed of data order and item randomness.
        inputs: the network's input contract (``model.network_config.inputs``), which
            says how the items are drawn (:func:`build_datasets`); None:
            ``InputConfig()``.
    """

    def __init__(self, config: DataConfig, seed: int = 0,
                 inputs: InputConfig | None = None) -> None:
        super().__init__()
        self.config, self.seed = config, int(seed)
        self.inputs = InputConfig() if inputs is None else inputs
        self.train_set: IndexedConcat | None = None
        self.val_set: IndexedConcat | None = None

    def setup(self, stage: str | None = None) -> None:
        """Open the sources and split them (once)."""
        if self.train_set is None:
            self.train_set, self.val_set = build_datasets(self.config, self.seed, self.inputs)

    def _rank_world(self) -> tuple[int, int]:
        trainer = self.trainer
        if trainer is None:
            return 0, 1
        return trainer.global_rank, trainer.world_size

    def train_dataloader(self) -> ResumableDataLoader:
        """Shuffled, sharded over processes, padded so all ranks take the same steps."""
        self.setup()
        rank, world = self._rank_world()
        sampler = ShardedSampler(len(self.train_set), True, self.seed, rank, world, pad=True)
        if len(sampler) < self.config.batch_size:
            raise ValueError(f"data.batch_size={self.config.batch_size} is larger than the "
                             f"{len(sampler)} training frames per process")
        return ResumableDataLoader(self.train_set, sampler, batch_size=self.config.batch_size,
                                   num_workers=self.config.num_workers, drop_last=True,
                                   pin_memory=torch.cuda.is_available(),
                                   collate_fn=collate_frames)

    def val_dataloader(self, rank_world: tuple[int, int] | None = None) -> DataLoader:
        """In order, sharded over processes without repeats (this process's shard, or
        that of ``rank_world`` = (rank, world size))."""
        self.setup()
        rank, world = rank_world or self._rank_world()
        sampler = ShardedSampler(len(self.val_set), False, self.seed, rank, world, pad=False)
        return DataLoader(self.val_set, batch_size=self.config.val_batch_size, sampler=sampler,
                          num_workers=self.config.num_workers, collate_fn=collate_frames)

    def check_val_frames(self, rank: int, world: int,
                         limit: int | float | None = None) -> None:
        """Read and batch this process's validation frames once before training, as the
        validation will (``limit``: ``trainer.limit_val_batches``, 0 for none): a missing
        or corrupt frame, or frames that cannot share a batch, then fail at once and not
        after the first epoch's training."""
        if self.val_set is None or not len(self.val_set) or limit == 0:
            return
        loader = self.val_dataloader((rank, world))
        batches = len(loader) if limit is None else (
            min(int(limit), len(loader)) if isinstance(limit, int)
            else max(1, int(limit * len(loader))))
        for _ in itertools.islice(loader, batches):
            pass
