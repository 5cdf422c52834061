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
