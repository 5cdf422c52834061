"""Training runs (deltar.training.run): fine-tuning from earlier weights on ZJU-L5-layout
data, a run killed mid-epoch resuming on the same loss curve, and DDP over two CPU
processes (gloo, launched with torchrun as docs/training.md describes). The CLI:
tests/cli/test_train.py."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from deltar.data.zju_l5 import ZJUL5Sample, write_zju_l5
from deltar.io.resources import cpu_count
from deltar.models import create_model
from deltar.training.module import export_model
from deltar.training.run import build_data_module, build_system, train
from deltar.training.run_folder import read_history

HERE = Path(__file__).resolve().parent
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "tiny_test.yaml"
TINY_MODEL = {"decoder_channels": [32, 32, 16, 16, 8], "head_channels": 16, "n_bins": 16,
              "head": "bins",
              "design_size": [64, 96]}


def _write_zju(folder, frames, rng):
    rects = np.array([[r * 16, c * 24, r * 16 + 16, c * 24 + 24] for r in range(4)
                      for c in range(4)], dtype=np.float32)
    samples = []
    for i in range(frames):
        depth = rng.uniform(0.8, 3.0, (64, 96)).astype(np.float32)
        mean = np.array([depth[int(y0):int(y1), int(x0):int(x1)].mean()
                         for y0, x0, y1, x1 in rects], dtype=np.float32)
        samples.append(ZJUL5Sample(
            rgb=rng.integers(0, 255, (64, 96, 3), dtype=np.uint8), depth_m=depth,
            zone_mean_sigma=np.stack([mean, np.full(16, 0.05, np.float32)], 1),
            zone_rects=rects, zone_valid=np.ones(16, bool), name=f"scene/{i:05d}"))
    return write_zju_l5(folder, samples, split="train")


def test_finetune_on_zju_layout_starts_from_given_weights(tmp_path, rng, tiny_config):
    data_json = _write_zju(tmp_path / "zju", 6, rng)
    torch.manual_seed(123)
    start = create_model("deltar-lite", **TINY_MODEL)
    weights = tmp_path / "start.pt"
    torch.save(export_model(start, "deltar-lite"), weights)
    config = tiny_config(
        f"model.init_checkpoint={weights}", "data.sources.0.kind=zju_l5",
        f"data.sources.0.path={data_json.parent}", "data.sources.0.split=train",
        "data.sources.0.resize=null", "data.sources.0.holdout_fraction=0.34",
        "trainer.max_epochs=1", "data.sampling=icdf")

    system = build_system(config)
    for (name, a), b in zip(system.model.state_dict().items(), start.state_dict().values(),
                            strict=True):
        torch.testing.assert_close(a, b, msg=name)

    run = train(config, tmp_path / "run")
    history = read_history(run / "history" / "rank0.jsonl")
    assert sorted(history) == [1, 2]  # 4 training frames (last 2 held out), batch 2
    assert sorted(i for r in history.values() for i in r["indices"]) == [0, 1, 2, 3]


@pytest.mark.parametrize("from_histograms", [False, True])
def test_the_data_draws_hypotheses_as_the_network_was_configured(tiny_config,
                                                                  from_histograms):
    config = tiny_config(f"model.overrides.histogram_hypotheses={str(from_histograms).lower()}")
    system = build_system(config)
    assert system.model.network_config.inputs.histogram_hypotheses is from_histograms
    inputs = build_data_module(config, system).inputs
    assert inputs.histogram_hypotheses is from_histograms
    # The images are normalised as the network's contract says, too.
    assert inputs.image_mean == system.model.network_config.inputs.image_mean


def test_a_switch_given_as_text_is_read_as_written_or_refused(tiny_config):
    """A quoted YAML value is text: 'false' stays off; other text is an error naming it."""
    off = tiny_config("model.overrides.histogram_hypotheses='false'")
    assert build_system(off).model.network_config.inputs.histogram_hypotheses is False
    with pytest.raises(ValueError, match="histogram_hypotheses must be true or false"):
        build_system(tiny_config("model.overrides.histogram_hypotheses=maybe"))


def test_fine_tuning_says_when_it_reads_the_zones_otherwise(tmp_path, tiny_config):
    start = create_model("deltar-lite", **TINY_MODEL, histogram_hypotheses=True)
    weights = tmp_path / "start.pt"
    torch.save(export_model(start, "deltar-lite"), weights)
    with pytest.warns(UserWarning, match="input settings: histogram_hypotheses true -> false"):
        build_system(tiny_config(f"model.init_checkpoint={weights}"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        build_system(tiny_config(f"model.init_checkpoint={weights}",
                                 "model.overrides.histogram_hypotheses=true"))
    # Another hypothesis sampling, and a fitted output stage the new run does not keep.
    start.set_output_contract(zone_consistency=0.5)
    torch.save(export_model(start, "deltar-lite"), weights)
    with pytest.warns(UserWarning) as caught:
        build_system(tiny_config(f"model.init_checkpoint={weights}",
                                 "model.overrides.histogram_hypotheses=true",
                                 "model.overrides.hypothesis_sampling=uniform"))
    said = " ".join(str(w.message) for w in caught)
    assert "hypothesis_sampling icdf -> uniform" in said
    assert "fitted output stage (zone_consistency)" in said and "fit-uncertainty" in said


def test_init_checkpoint_takes_a_bundled_name_and_names_another_preset(tiny_config):
    with pytest.raises(ValueError, match="holds a deltar-select network; the configuration "
                                         r"builds a deltar-lite \(model.preset\)"):
        build_system(tiny_config("model.init_checkpoint=default"))


def test_init_checkpoint_of_another_architecture_is_rejected(tmp_path, tiny_config):
    other = create_model("deltar-lite", **{**TINY_MODEL, "n_bins": 8})
    weights = tmp_path / "other.pt"
    torch.save(export_model(other, "deltar-lite"), weights)
    try:
        build_system(tiny_config(f"model.init_checkpoint={weights}"))
    except ValueError as err:
        assert "do not fit the configured model" in str(err)
    else:
        raise AssertionError("mismatching weights were accepted")


# 8 training frames, batch 2: 4 steps per epoch, 2 epochs (8 steps).
@pytest.mark.parametrize(("every", "kill_at", "checkpoint_step", "move"), [
    (3, 4, 3, False),  # killed in step 5; newest checkpoint: step 3, in the middle of epoch 0
    (2, 5, 4, True),  # killed in step 6; newest checkpoint: step 4, the end of epoch 0; the
    # folder then moved (e.g. from scratch space to a shared disk) before the resume
])
def test_killed_run_resumes_on_the_same_loss_curve(tmp_path, tiny_config, every, kill_at,
                                                   checkpoint_step, move):
    overrides = (f"trainer.checkpoint_every_n_steps={every}",)
    config = tiny_config(*overrides)
    reference = train(config, tmp_path / "uninterrupted")

    killed = tmp_path / "killed"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, str(HERE / "killable_run.py"), str(killed),
                             str(kill_at), *overrides], env=env, capture_output=True,
                            text=True, timeout=300, check=False)
    assert result.returncode == -signal.SIGKILL, result.stderr[-2000:]
    last = torch.load(killed / "checkpoints" / "last.ckpt", weights_only=False)
    assert last["global_step"] == checkpoint_step and last["epoch"] == 0
    assert not (killed / "model.pt").exists()
    before = read_history(killed / "history" / "rank0.jsonl")
    assert sorted(before) == list(range(1, kill_at + 1))

    logged = (killed / "logs" / "csv" / "metrics.csv").read_text(encoding="utf-8")
    if move:
        (tmp_path / "moved").mkdir()
        killed = killed.rename(tmp_path / "moved" / "killed")

    train(config, killed, resume=True)

    # The folder's files carry on: last.ckpt is the newest (no last-v1.ckpt beside a
    # stale one), old step checkpoints are pruned, the CSV log keeps its earlier rows.
    names = sorted(p.name for p in (killed / "checkpoints").iterdir())
    kept = {2: ["step=6.ckpt", "step=8.ckpt"], 3: ["step=3.ckpt", "step=6.ckpt"]}[every]
    assert names == ["last.ckpt", *kept]  # keep_checkpoints: 2
    assert torch.load(killed / "checkpoints" / "last.ckpt", weights_only=False)[
        "global_step"] == int(kept[-1][5:-5])
    rows = (killed / "logs" / "csv" / "metrics.csv").read_text(encoding="utf-8")
    assert rows.startswith(logged.rstrip("\n")) or not logged.strip()
    assert len(rows.splitlines()) > len(logged.splitlines())

    expected = read_history(reference / "history" / "rank0.jsonl")
    resumed = read_history(killed / "history" / "rank0.jsonl")  # later lines win
    assert sorted(resumed) == sorted(expected) == list(range(1, 9))
    for step in expected:
        assert resumed[step]["indices"] == expected[step]["indices"], step
        assert resumed[step]["loss"] == pytest.approx(expected[step]["loss"], rel=1e-5), step
    final = [json.loads((run / "history" / "rank0_final.json").read_text(encoding="utf-8"))
             for run in (reference, killed)]
    assert final[0] == final[1]  # same step, bit-identical parameters


@pytest.mark.skipif(cpu_count() < 2, reason="two training processes need two CPUs "
                    "(deltar train refuses more CPU devices than the machine has)")
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
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=300,
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


def _signal_at_step(step: int, signum: int):
    """A Lightning callback sending this process ``signum`` when step ``step`` starts."""
    import lightning as L

    class SignalAtStep(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
            if trainer.global_step == step:
                os.kill(os.getpid(), signum)

    return SignalAtStep()


def test_a_run_stopped_by_sigterm_says_so_and_resumes(tmp_path, tiny_config):
    """A scheduler's SIGTERM ends the run as a failure naming how to go on (Lightning
    alone ends it as a success), and the run then resumes to the end."""
    from deltar.training.run import TrainingInterrupted

    config = tiny_config("trainer.checkpoint_every_n_steps=2")
    run = tmp_path / "run"
    with pytest.raises(TrainingInterrupted, match=r"stopped by SIGTERM at step \d.*no model\.pt "
                                                  r"written.*deltar train --resume") as stop:
        train(config, run, extra_callbacks=[_signal_at_step(3, signal.SIGTERM)])
    assert stop.value.exit_code == 128 + signal.SIGTERM
    assert not (run / "model.pt").exists()
    train(config, run, resume=True)
    assert sorted(read_history(run / "history" / "rank0.jsonl")) == list(range(1, 9))
    assert (run / "model.pt").is_file()


def test_a_callback_that_exits_is_not_taken_for_a_signal(tmp_path, tiny_config):
    import lightning as L

    class Exit(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
            if trainer.global_step == 2:
                sys.exit(0)

    with pytest.raises(SystemExit) as stop:
        train(tiny_config(), tmp_path / "run", extra_callbacks=[Exit()])
    assert type(stop.value) is SystemExit and stop.value.code == 0


def test_a_resume_refuses_a_config_edited_in_what_the_run_learns(tmp_path, tiny_config):
    """The checkpoint keeps the settings the run started with: an edit that changes what
    it learns is refused by name (it would be silently ignored and misdescribe the run);
    one of where or how it runs is not."""
    config = tiny_config("trainer.checkpoint_every_n_steps=2", "trainer.max_epochs=1")
    run = train(config, tmp_path / "run")
    edited = tiny_config("trainer.checkpoint_every_n_steps=2", "trainer.max_epochs=1",
                         "optim.lr=0.5", "data.signal_augmentation.enabled=false")
    (run / "config.yaml").write_text(edited.to_yaml(), encoding="utf-8")  # by hand
    with pytest.raises(ValueError, match=r"config\.yaml was edited after the run started "
                                         r"\(data\.signal_augmentation\.enabled, optim\.lr\)"):
        train(edited, run, resume=True)
    shown = tiny_config("trainer.checkpoint_every_n_steps=2", "trainer.max_epochs=1",
                        "trainer.progress_bar=true", "data.num_workers=0")
    (run / "config.yaml").write_text(shown.to_yaml(), encoding="utf-8")
    with pytest.warns(UserWarning, match="has finished"):
        train(shown, run, resume=True)


def test_a_resume_from_a_checkpoint_of_another_network_names_what_differs(tmp_path,
                                                                           tiny_config):
    """A checkpoint of another network (copied from another run, or saved before the run
    kept its config in checkpoints) is refused before training, naming the checkpoint,
    the setting and the tensors that differ; not a traceback from Lightning's load."""
    settings = ("trainer.checkpoint_every_n_steps=2", "trainer.max_epochs=1")
    run = train(tiny_config(*settings), tmp_path / "run")
    other = train(tiny_config(*settings, "model.overrides.head_channels=8"), tmp_path / "b")
    last = run / "checkpoints" / "last.ckpt"
    state = torch.load(other / "checkpoints" / "last.ckpt", weights_only=False)
    for keep_config in (True, False):
        if not keep_config:
            del state["deltar_train_config"]
        torch.save(state, last)
        with pytest.raises(ValueError, match=rf"^{last}: its network is not the one "
                           rf"{run / 'config.yaml'} builds \(decoder\.out_channels 8 in the "
                           r"checkpoint, 16 configured; \d+ tensor\(s\) of other shapes "
                           r"\(model\.decoder\.out_conv\.weight: \[8, 8, 3, 3\] in the "
                           r"checkpoint, \[16, 8, 3, 3\] configured"):
            train(tiny_config(*settings), run, resume=True)


def test_network_mismatch_names_missing_and_unexpected_tensors():
    from deltar.training.run_folder import network_mismatch

    system = torch.nn.Sequential(torch.nn.Linear(2, 3))
    state = dict(system.state_dict())
    assert network_mismatch({"state_dict": state}, system) is None
    state["1.weight"] = state.pop("0.bias")
    assert network_mismatch({"state_dict": state}, system) == (
        "1 tensor(s) missing from the checkpoint (0.bias); 1 tensor(s) unexpected (1.weight)")


def test_a_resume_reads_no_starting_weights(tmp_path, tiny_config):
    """A run started from other weights resumes after those have moved or gone: every
    weight comes from its checkpoint."""
    from deltar.training.run import TrainingInterrupted

    start = train(tiny_config("trainer.max_epochs=1"), tmp_path / "start") / "model.pt"
    config = tiny_config("trainer.checkpoint_every_n_steps=2", f"model.init_checkpoint={start}")
    run = tmp_path / "run"
    with pytest.raises(TrainingInterrupted):
        train(config, run, extra_callbacks=[_signal_at_step(3, signal.SIGTERM)])
    start.unlink()
    # A kill while saving leaves a partial checkpoint behind; the resume removes it.
    partial = run / "checkpoints" / ".last.ckpt.x1y2z3.tmp.ckpt"
    partial.write_bytes(b"\0" * 1024)
    train(config, run, resume=True)
    assert (run / "model.pt").is_file() and not partial.exists()


def test_config_changes_name_what_a_resume_may_not_change():
    from deltar.training.run_folder import config_changes

    saved = {"optim": {"betas": [0.9, 0.999], "lr": 1e-3},
             "trainer": {"devices": 1, "num_threads": 1},
             "data": {"sources": [{"path": "/scratch/a", "frames": 10}]}}
    same = {"optim": {"betas": (0.9, 0.999), "lr": 1e-3},  # a config built in code
            "trainer": {"devices": 1, "num_threads": 2},
            "data": {"sources": [{"path": "/shared/a", "frames": 10}]}}
    assert config_changes(saved, same) == []
    other = {**same, "trainer": {"devices": 2, "num_threads": 1},
             "data": {"sources": [{"path": "/shared/a", "frames": 12}]}}
    assert config_changes(saved, other) == ["data.sources.0.frames", "trainer.devices"]


@pytest.mark.parametrize(("override", "message"), [
    ("trainer.val_check_interval=100", r"trainer.val_check_interval is 100 steps but an "
                                       r"epoch trains 4 batches per process"),
    ("trainer.limit_val_batches=0.5", r"trainer.limit_val_batches 0.5 of the 1 validation "
                                      r"batches per process is less than one batch"),
])
def test_validation_limits_lightning_refuses_late_are_refused_before_the_run(
        tmp_path, tiny_config, override, message):
    # Lightning refused them once training started (the fraction: after an epoch, with a
    # traceback), leaving a run folder that a new start then refused.
    run = tmp_path / "run"
    with pytest.raises(ValueError, match=message):
        train(tiny_config(override), run)
    assert not (run / "config.yaml").exists() and not (run / "checkpoints").exists()
