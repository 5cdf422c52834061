"""DDP: two CPU processes (gloo) launched with torchrun, as docs/training.md describes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from deltar.training.run import read_history

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "tiny_test.yaml"


def test_two_processes_share_the_data_and_end_with_identical_weights(tmp_path):
    deltar = shutil.which("deltar")
    assert deltar, "the deltar console script is not installed"
    run = tmp_path / "run"
    # 8 training frames, 2 per batch and process: 2 steps per epoch, 6 epochs. No
    # augmentation, so each epoch's mean loss is over the very same inputs.
    command = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
        "--no-python", deltar, "train", "--config", str(CONFIG), "--run-dir", str(run),
        "-o", "trainer.strategy=ddp", "-o", "trainer.devices=2", "-o", "trainer.max_epochs=6",
        "-o", "trainer.val_every_n_epochs=6", "-o", "optim.lr=2e-3",
        "-o", "data.image_augmentation.enabled=false",
        "-o", "data.signal_augmentation.enabled=false",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=150,
                            check=False)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]

    histories = [read_history(run / "history" / f"rank{r}.jsonl") for r in (0, 1)]
    assert sorted(histories[0]) == sorted(histories[1]) == list(range(1, 13))
    for epoch in range(6):
        shards = [sorted(i for rec in h.values() if rec["epoch"] == epoch
                         for i in rec["indices"]) for h in histories]
        # Each process saw a different half of the 8 training frames.
        assert not set(shards[0]) & set(shards[1])
        assert sorted(shards[0] + shards[1]) == list(range(8))

    finals = [json.loads((run / "history" / f"rank{r}_final.json").read_text(encoding="utf-8"))
              for r in (0, 1)]
    assert finals[0] == finals[1]  # same step count and bit-identical parameters

    def epoch_loss(epoch):
        return np.mean([rec["loss"] for h in histories for rec in h.values()
                        if rec["epoch"] == epoch])

    assert epoch_loss(5) < 0.9 * epoch_loss(0)
    assert (run / "model.pt").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
