"""Configuration values Lightning, PyTorch or numpy would refuse only once a run started."""

from __future__ import annotations

from pathlib import Path

import pytest

from deltar.training.config_loading import load_config

#: A valid configuration (procedural rooms) the overrides change.
TINY = Path(__file__).parents[2] / "configs" / "tiny_test.yaml"


@pytest.mark.parametrize(("override", "message"), [
    ("optim.lr=.inf", "optim.lr must be a finite number, got inf"),
    ("optim.weight_decay=.nan", "optim.weight_decay must be a finite number, got nan"),
    ("data.layout_jitter_px=.nan", "data.layout_jitter_px must be a finite number"),
    ("optim.betas=[2.0, -1]", r"optim.betas must be two numbers in \[0, 1\), got \[2.0, -1"),
    ("optim.base_momentum=-5", r"optim.base_momentum must be in \[0, 1\], got -5"),
    ("seed=-3", "seed must be in 0..4294967295, got -3"),
    ("trainer.keep_checkpoints=-7", "trainer.keep_checkpoints must be >= 0, or -1 for all"),
    ("trainer.val_every_n_epochs=0", "trainer.val_every_n_epochs must be >= 1, got 0"),
    ("trainer.val_check_interval=0", "trainer.val_check_interval must be >= 1 step or null"),
    ("trainer.limit_train_batches=-1", "trainer.limit_train_batches must be a number of "
     r"batches >= 1, a fraction in \(0, 1\] or null, got -1"),
    ("trainer.limit_val_batches=1.5", "trainer.limit_val_batches must be a number"),
    ("trainer.precision=8-bit", "trainer.precision must be one of"),
    ("trainer.accelerator=tpuu", "trainer.accelerator must be one of"),
    # Lightning's names that training does not support (tpu: a torch_xla error, no key).
    ("trainer.accelerator=tpu", r"trainer\.accelerator must be one of \('auto', 'cpu', 'gpu', "
     r"'cuda', 'mps'\), got 'tpu'"),
    ("trainer.accelerator=hpu", "trainer.accelerator must be one of"),
])
def test_values_a_run_would_fail_on_are_refused_naming_the_key(override, message):
    with pytest.raises(ValueError, match=message):
        load_config(TINY, [override])


def test_the_values_lightning_takes_pass():
    config = load_config(TINY, [
        "trainer.keep_checkpoints=-1", "trainer.limit_train_batches=0.5",
        "trainer.limit_val_batches=3", "trainer.precision=bf16-mixed",
        "trainer.accelerator=gpu", "trainer.val_check_interval=50", "seed=4294967295"])
    assert config.trainer.limit_train_batches == 0.5
    for off in ("0", "0.0"):  # validation switched off, as Lightning allows
        load_config(TINY, [f"trainer.limit_val_batches={off}"])
    with pytest.raises(ValueError, match="limit_train_batches must be"):
        load_config(TINY, ["trainer.limit_train_batches=0"])


@pytest.mark.parametrize(("overrides", "message"), [
    # 50 zones of 12 px (600 px) on 64 x 96 procedural frames.
    (["data.training_grid=50"], r"data\.training_grid x data\.training_zone_px \(50 x 12 = 600 "
     r"px\) is wider than the 64x96 images the network reads from data\.sources\.0 "
     r"\(procedural, 10 frames from seed 0\): the outer zones"),
    # Only the validation frames read the training layout: checked on them.
    (["data.zone_layout=calibrated", "data.val_zone_layout=training", "data.training_grid=8"],
     r"\(8 x 12 = 96 px\) is wider than the 64x96 images"),
    (["data.image_augmentation.crop=[96, 96]"],
     r"data\.image_augmentation\.crop \[96, 96\] is larger than the 64x96 frames"),
    # The 48 px grid on 64 px high frames: 8 px of room on each side.
    (["data.training_max_offset_px=9"],
     r"data\.training_max_offset_px 9 would shift the 48 px zone grid off the 64x96 images "
     r"the network trains on from data\.sources\.0 .*: at most 8 px"),
    (["data.training_max_offset_px=100000"], "data.training_max_offset_px 100000"),
    (["data.layout_jitter_px=32"],
     r"data\.layout_jitter_px 32\.0 is not less than half the smaller side of the 64x96 "
     r"images the network trains on from data\.sources\.0"),
])
def test_a_layout_or_crop_larger_than_the_frames_is_refused_before_training(overrides,
                                                                           message):
    from deltar.training.data import build_datasets

    config = load_config(TINY, overrides)
    with pytest.raises(ValueError, match=message):
        build_datasets(config.data, seed=0)


def test_the_tiny_layout_fits_its_frames():
    from deltar.training.data import build_datasets

    train, val = build_datasets(load_config(TINY, ["data.training_grid=5"]).data, seed=0)
    assert train[0]["zone_rects"].shape[0] == 25 and len(val) > 0
    # The largest offset and a jitter below half the 64 px side still train.
    train, _ = build_datasets(load_config(TINY, ["data.training_max_offset_px=8",
                                                 "data.layout_jitter_px=31.5"]).data, seed=0)
    assert train[0]["zone_rects"].shape[0] == 16


@pytest.mark.parametrize("scale", ["[1e-6, 1e-6]", "[0.05, 1.0]", "[1.0, 20.0]", "[0, 1]"])
def test_a_depth_scale_range_outside_0_1_to_10_is_refused(scale):
    with pytest.raises(ValueError, match=r"data\.depth_scale_range must be \[low, high\] "
                                         r"with 0\.1 <= low <= high <= 10\.0"):
        load_config(TINY, [f"data.depth_scale_range={scale}"])
    assert load_config(TINY, ["data.depth_scale_range=[0.1, 10]"]).data.depth_scale_range


@pytest.mark.parametrize(("override", "message"), [
    ("data.num_hypotheses=100000000", "data.num_hypotheses must be at most 1024, got 100000000"),
    ("data.sources.0.frames=100000000000", "data.sources.0.frames must be at most 10000000 for "
     "procedural sources, got 100000000000"),
])
def test_sizes_that_would_run_out_of_memory_are_refused(override, message):
    # Only the configuration is read: nothing of that size is built.
    with pytest.raises(ValueError, match=message):
        load_config(TINY, [override])
    largest = load_config(TINY, ["data.num_hypotheses=1024", "data.sources.0.frames=10000000"])
    assert largest.data.num_hypotheses == 1024
