"""Run the tiny training and SIGKILL the process when a given step starts.

Usage: ``python killable_run.py RUN_DIR KILL_AT_STEP [key=value ...]``; used by
test_run.py to interrupt a run the hard way (no handler, no cleanup).
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import lightning as L

from deltar.training.config_loading import load_config
from deltar.training.run import train

TINY_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "tiny_test.yaml"


class KillAtStep(L.Callback):
    """SIGKILL this process when optimiser step ``step + 1`` is about to run."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGKILL)


if __name__ == "__main__":
    run_dir, kill_at, *overrides = sys.argv[1:]
    config = load_config(TINY_CONFIG, overrides)
    train(config, run_dir, extra_callbacks=[KillAtStep(int(kill_at))])
