"""Checks of training-configuration values that Lightning, PyTorch or numpy would only
refuse after the run had started (a traceback after an epoch, and a run folder left
behind): every number finite, and the trainer's limits in the ranges Lightning takes.
Each names the dotted key; :meth:`deltar.training.config.TrainConfig.validate` runs them.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

#: Lightning's precision names (``Trainer(precision=...)``).
PRECISIONS: tuple[str, ...] = ("64-true", "64", "32-true", "32", "16-mixed", "16",
                               "bf16-mixed", "bf16", "16-true", "bf16-true",
                               "transformer-engine", "transformer-engine-float16")
#: Upper bounds no real run reaches (the presets use 16 hypotheses, the recipes 200
#: procedural frames); above them building the data would end out of memory.
MAX_HYPOTHESES = 1024
MAX_PROCEDURAL_FRAMES = 10_000_000
#: The accelerators training supports (Lightning's names, ``Trainer(accelerator=...)``):
#: not ``tpu`` nor ``hpu``, which need torch_xla / Habana packages and code paths (e.g. the
#: random-state saving of :mod:`deltar.training.module`) it does not have.
ACCELERATORS: tuple[str, ...] = ("auto", "cpu", "gpu", "cuda", "mps")


def check_finite(section: Any, where: str) -> None:
    """Refuse NaN or infinite numbers anywhere in a config section (dataclasses, lists
    and dicts walked), naming the dotted key: ``optim.lr=inf`` would train an epoch into
    NaN weights before anything said so."""
    if dataclasses.is_dataclass(section):
        for item in dataclasses.fields(section):
            check_finite(getattr(section, item.name), f"{where}.{item.name}")
    elif isinstance(section, dict):
        for key, value in section.items():
            check_finite(value, f"{where}.{key}")
    elif isinstance(section, list | tuple):
        for index, value in enumerate(section):
            check_finite(value, f"{where}[{index}]")
    elif isinstance(section, float) and not math.isfinite(section):
        raise ValueError(f"{where} must be a finite number, got {section}")


def check_data_sizes(data: Any, where: str) -> None:
    """The data section's sizes below the bounds no real run reaches: ``num_hypotheses``
    (K per zone, <= :data:`MAX_HYPOTHESES`) and each procedural source's ``frames``
    (<= :data:`MAX_PROCEDURAL_FRAMES`), which would otherwise end in an out-of-memory
    traceback once the data is built."""
    if data.num_hypotheses > MAX_HYPOTHESES:
        raise ValueError(f"{where}.num_hypotheses must be at most {MAX_HYPOTHESES}, got "
                         f"{data.num_hypotheses}")
    for number, source in enumerate(data.sources):
        if source.kind == "procedural" and source.frames > MAX_PROCEDURAL_FRAMES:
            raise ValueError(f"{where}.sources.{number}.frames must be at most "
                             f"{MAX_PROCEDURAL_FRAMES} for procedural sources, got "
                             f"{source.frames}")


def check_trainer_limits(trainer: Any, where: str) -> None:
    """The trainer section's values Lightning would refuse at run time: checkpoints to
    keep, validation intervals, batch limits, precision and accelerator names."""
    if trainer.keep_checkpoints < -1:
        raise ValueError(f"{where}.keep_checkpoints must be >= 0, or -1 for all, got "
                         f"{trainer.keep_checkpoints}")
    if trainer.val_every_n_epochs < 1:
        raise ValueError(f"{where}.val_every_n_epochs must be >= 1, got "
                         f"{trainer.val_every_n_epochs}")
    if trainer.val_check_interval is not None and trainer.val_check_interval < 1:
        raise ValueError(f"{where}.val_check_interval must be >= 1 step or null, got "
                         f"{trainer.val_check_interval}")
    for name, off in (("limit_train_batches", False), ("limit_val_batches", True)):
        limit = getattr(trainer, name)
        if not _batch_limit_ok(limit, off):
            raise ValueError(f"{where}.{name} must be a number of batches >= 1, a fraction "
                             f"in (0, 1]{', 0 (no validation)' if off else ''} or null, got "
                             f"{limit}")
    for name, value, names in (("precision", trainer.precision, PRECISIONS),
                               ("accelerator", trainer.accelerator, ACCELERATORS)):
        if str(value) not in names:
            raise ValueError(f"{where}.{name} must be one of {names}, got {value!r}")


def _batch_limit_ok(limit: Any, zero_allowed: bool) -> bool:
    """A Lightning batch limit: None (all), whole batches >= 1, a fraction in (0, 1], and
    where ``zero_allowed`` 0 (validation switched off)."""
    if limit is None:
        return True
    if isinstance(limit, bool) or not isinstance(limit, int | float):
        return False
    if limit == 0:
        return zero_allowed
    return limit >= 1 if isinstance(limit, int) else 0.0 < limit <= 1.0



def check_frames_fit(data: Any, frame_size: tuple[int, int], number: int, source: Any) -> None:
    """A data source's frames against the data section, before any training: a random
    crop larger than the frames it crops, or a ``training`` zone layout (``training_grid``
    x ``training_zone_px`` pixels, centred) wider than the images the network reads from
    them (the crop, or whole frames), whose outer zones would lie off the image; for the
    training images, a ``training_max_offset_px`` that could shift that grid off them, or a
    ``layout_jitter_px`` of half their smaller side or more (the layout the network is
    given could be centred off the image).

    Args:
        data: the ``data`` section (:class:`~deltar.training.config.DataConfig`).
        frame_size: (height, width) pixels of the source's frames.
        number: the source's index in ``data.sources``; ``source`` its section.
    """
    where = f"data.sources.{number} ({source.label()})"
    crop = data.image_augmentation.crop if data.image_augmentation.enabled else None
    if crop is not None and source.role != "val" and (
            crop[0] > frame_size[0] or crop[1] > frame_size[1]):
        raise ValueError(f"data.image_augmentation.crop {list(crop)} is larger than the "
                         f"{frame_size[0]}x{frame_size[1]} frames of {where}")
    read = []  # (the images the network reads, their zone layout, trained on) per use
    if source.role != "val":
        read.append((frame_size if crop is None else tuple(crop), data.zone_layout, True))
    if source.role != "train":
        read.append((frame_size, data.val_zone_layout or data.zone_layout, False))
    side = data.training_grid * data.training_zone_px
    for (height, width), layout, train in read:
        if layout == "training" and side > min(height, width):
            raise ValueError(f"data.training_grid x data.training_zone_px ("
                             f"{data.training_grid} x {data.training_zone_px} = {side} px) "
                             f"is wider than the {height}x{width} images the network reads "
                             f"from {where}: the outer zones would lie off the image; "
                             "lower either")
        if not train:  # validation items are neither shifted nor jittered
            continue
        offset = data.training_max_offset_px
        if layout == "training" and side + 2 * offset > min(height, width):
            raise ValueError(f"data.training_max_offset_px {offset} would shift the {side} px "
                             f"zone grid off the {height}x{width} images the network trains "
                             f"on from {where}: at most {(min(height, width) - side) // 2} px "
                             "keeps it on the image")
        if data.layout_jitter_px >= min(height, width) / 2:
            raise ValueError(f"data.layout_jitter_px {data.layout_jitter_px} is not less than "
                             f"half the smaller side of the {height}x{width} images the "
                             f"network trains on from {where}: the zone layout it is given "
                             "could be centred off the image (a calibration error is a few "
                             "pixels)")
