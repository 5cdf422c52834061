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


# 8 training frames, batch 2: 4 steps per epoch, 2 epochs (8 steps).
@pytest.mark.parametrize(("every", "kill_at", "checkpoint_step"), [
    (3, 4, 3),  # killed in step 5; newest checkpoint: step 3, in the middle of epoch 0
    (2, 5, 4),  # killed in step 6; newest checkpoint: step 4, the end of epoch 0
])
def test_killed_run_resumes_on_the_same_loss_curve(tmp_path, tiny_config, every, kill_at,
                                                   checkpoint_step):
    overrides = (f"trainer.checkpoint_every_n_steps={every}",)
    config = tiny_config(*overrides)
    reference = train(config, tmp_path / "uninterrupted")

    killed = tmp_path / "killed"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, str(HERE / "killable_run.py"), str(killed),
                             str(kill_at), *overrides], env=env, capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == -signal.SIGKILL, result.stderr[-2000:]
    last = torch.load(killed / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == checkpoint_step and last["epoch"] == 0
    assert not (killed / "model.pt").exists()
    before = read_history(killed / "history" / "rank0.jsonl")
    assert sorted(before) == list(range(1, kill_at + 1))

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
