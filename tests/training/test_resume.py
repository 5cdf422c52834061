"""A run killed mid-epoch resumes from its last checkpoint on the same loss curve."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from deltar.training.run import read_history, train

HERE = Path(__file__).resolve().parent
# 8 training frames, batch 2: 4 steps per epoch, 2 epochs; checkpoints at steps 3 and 6.
OVERRIDES = ("trainer.checkpoint_every_n_steps=3",)


def test_killed_run_resumes_on_the_same_loss_curve(tmp_path, tiny_config):
    config = tiny_config(*OVERRIDES)
    reference = train(config, tmp_path / "uninterrupted")

    killed = tmp_path / "killed"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # Killed while step 5 runs: the newest checkpoint is step 3, in the middle of epoch 0.
    result = subprocess.run([sys.executable, str(HERE / "killable_run.py"), str(killed), "4",
                             *OVERRIDES], env=env, capture_output=True, text=True,
                            timeout=120, check=False)
    assert result.returncode == -signal.SIGKILL, result.stderr[-2000:]
    last = torch.load(killed / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == 3 and last["epoch"] == 0
    assert not (killed / "model.pt").exists()
    before = read_history(killed / "history" / "rank0.jsonl")
    assert sorted(before) == [1, 2, 3, 4]

    train(config, killed, resume=True)

    expected = read_history(reference / "history" / "rank0.jsonl")
    resumed = read_history(killed / "history" / "rank0.jsonl")  # later lines win
    assert sorted(resumed) == sorted(expected) == list(range(1, 9))
    for step in expected:
        assert resumed[step]["indices"] == expected[step]["indices"], step
        assert resumed[step]["loss"] == pytest.approx(expected[step]["loss"], rel=1e-5), step
    final = [json.loads((run / "history" / "rank0_final.json").read_text(encoding="utf-8"))
             for run in (reference, killed)]
    assert final[0] == final[1]  # same step, bit-identical parameters
