"""DeltarSystem (loss, optimiser, schedule) and a tiny end-to-end run on CPU."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
import yaml

from deltar.training.config import OptimConfig
from deltar.training.config_loading import config_from_dict
from deltar.training.module import DeltarSystem, load_trained_model
from deltar.training.run import train
from deltar.training.run_folder import AtomicCheckpointIO, read_history

TINY_MODEL = {"decoder_channels": [32, 32, 16, 16, 8], "head_channels": 16, "n_bins": 16,
              "head": "bins",
              "design_size": [64, 96]}


@pytest.fixture(scope="module")
def system():
    torch.manual_seed(0)
    return DeltarSystem("deltar-lite", TINY_MODEL, OptimConfig(lr=2e-3))


def _reference_loss(pred, gt, alpha=10.0, lam=0.85):
    valid = gt > 1e-3
    g = np.log(pred[valid]) - np.log(gt[valid])
    return alpha * math.sqrt(np.mean(g**2) - lam * np.mean(g) ** 2)


def test_loss_is_the_scaled_si_loss_on_valid_pixels(system, rng):
    gt = rng.uniform(0.5, 4.0, (2, 1, 8, 12)).astype(np.float32)
    gt[0, 0, :3] = 0.0  # invalid pixels must not count
    pred = rng.uniform(0.5, 4.0, (2, 1, 8, 12)).astype(np.float32)
    loss = system.loss(torch.from_numpy(pred), torch.from_numpy(gt))
    assert float(loss) == pytest.approx(_reference_loss(pred, gt), rel=1e-4)


def test_loss_upsamples_a_half_resolution_prediction(system, rng):
    gt = rng.uniform(0.5, 4.0, (1, 1, 8, 12)).astype(np.float32)
    pred = np.full((1, 1, 4, 6), 2.0, dtype=np.float32)  # constant: upsampling is exact
    loss = system.loss(torch.from_numpy(pred), torch.from_numpy(gt))
    assert float(loss) == pytest.approx(_reference_loss(np.full_like(gt, 2.0), gt), rel=1e-4)


def test_encoder_trains_at_a_tenth_of_the_learning_rate(system):
    groups = system.parameter_groups()
    assert [g["lr"] for g in groups] == pytest.approx([2e-4, 2e-3])
    ids = [id(p) for g in groups for p in g["params"]]
    assert len(ids) == len(set(ids)) == len(list(system.model.parameters()))
    assert {id(p) for p in groups[0]["params"]} == {
        id(p) for p in system.model.image_encoder.parameters()}


def test_a_frozen_encoder_keeps_its_weights_and_statistics():
    torch.manual_seed(0)
    frozen = DeltarSystem("deltar-lite", TINY_MODEL, OptimConfig(lr=1e-2, freeze_encoder=True))
    groups = frozen.parameter_groups()
    assert [g["name"] for g in groups] == ["decoder"]
    encoder = frozen.model.image_encoder
    before = {k: v.clone() for k, v in encoder.state_dict().items()}
    frozen.train()
    assert not encoder.training and frozen.model.decoder.training
    from tests.models.conftest import make_inputs

    image, hypotheses, rects, valid = make_inputs(batch=2, height=64, width=96)
    optimizer = torch.optim.AdamW([p for g in groups for p in g["params"]], lr=1e-2)
    for _ in range(2):
        out = frozen.model(image, hypotheses, rects, valid)
        out["depth"].mean().backward()
        optimizer.step()
        optimizer.zero_grad()
    after = encoder.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # batch-norm stats too
    assert all(p.grad is None for p in encoder.parameters())


def test_one_cycle_schedule_spans_the_run(system):
    system.schedule_steps = 40
    setup = system.configure_optimizers()
    optimizer, scheduler = setup["optimizer"], setup["lr_scheduler"]["scheduler"]
    peaks = [2e-4, 2e-3]
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([p / 25 for p in peaks])
    lrs = []
    for _ in range(39):  # the schedule's last step (index 39) has the final rate
        optimizer.step()
        scheduler.step()
        lrs.append(optimizer.param_groups[1]["lr"])
    assert max(lrs) == pytest.approx(2e-3, rel=1e-3)
    assert lrs[-1] == pytest.approx(2e-3 / 25 / 100, rel=1e-2)
    assert optimizer.param_groups[0]["weight_decay"] == pytest.approx(0.1)


def test_tiny_end_to_end_run(tmp_path, tiny_config):
    config = tiny_config("trainer.max_epochs=1", "ema.enabled=true", "ema.decay=0.5")
    run = train(config, tmp_path / "run")

    saved = yaml.safe_load((run / "config.yaml").read_text(encoding="utf-8"))
    assert config_from_dict(saved).to_dict() == config.to_dict()
    checkpoints = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert checkpoints == ["last.ckpt", "step=2.ckpt", "step=4.ckpt"]
    assert not list(run.rglob("*.tmp*"))  # atomic writes leave no temporaries

    history = read_history(run / "history" / "rank0.jsonl")
    assert sorted(history) == [1, 2, 3, 4]  # 8 training frames / batch 2
    trained = sorted(i for r in history.values() for i in r["indices"])
    assert trained == list(range(8))  # held-out frames 8, 9 never train

    with (run / "logs" / "csv" / "metrics.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    d1 = [float(r["val/d1"]) for r in rows if r.get("val/d1")]
    assert len(d1) == 1 and 0.0 <= d1[0] <= 1.0

    model = load_trained_model(str(run / "model.pt"))
    from_ckpt = load_trained_model(str(run / "checkpoints" / "last.ckpt"))
    for a, b in zip(model.state_dict().values(), from_ckpt.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b)  # both hold the EMA weights at the end
    # The checkpoint keeps the raw weights too, and they differ from the average.
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    raw, averaged = ckpt["current_model_state"], ckpt["state_dict"]
    assert raw.keys() == averaged.keys()
    assert any(not torch.equal(raw[k], averaged[k]) for k in raw if "weight" in k)

    # Resuming the finished run (a requeued job) trains nothing and keeps model.pt; one
    # without model.pt gets it from the checkpoint, with the averaged weights.
    saved_model = (run / "model.pt").read_bytes()
    with pytest.warns(UserWarning, match=r"has finished \(4 steps\); nothing left to train"):
        train(config, run, resume=True)
    assert (run / "model.pt").read_bytes() == saved_model
    (run / "model.pt").unlink()
    with pytest.warns(UserWarning, match="has finished"):
        train(config, run, resume=True)
    for a, b in zip(model.state_dict().values(),
                    load_trained_model(str(run / "model.pt")).state_dict().values(), strict=True):
        torch.testing.assert_close(a, b)
    # A longer schedule on resume is refused by name, not deep in the optimiser.
    longer = tiny_config("trainer.max_epochs=2", "ema.enabled=true", "ema.decay=0.5")
    (run / "config.yaml").write_text(longer.to_yaml(), encoding="utf-8")
    with pytest.raises(ValueError, match=r"schedule spans 4 steps, the configuration now "
                                         r"gives 8.*model\.init_checkpoint"):
        train(longer, run, resume=True)
    # A damaged last checkpoint names the others to resume from.
    (run / "checkpoints" / "last.ckpt").write_bytes(b"damaged")
    with pytest.raises(ValueError, match=r"last\.ckpt: cannot read training checkpoint: .*"
                                         r"step=2\.ckpt, step=4\.ckpt"):
        train(longer, run, resume=True)


def test_a_frozen_encoder_keeps_its_statistics_through_a_lightning_run(tmp_path, tiny_config):
    """Lightning sets the submodules' modes itself (fit start, after validation): the
    frozen encoder's batch norms must still not follow the training batches."""
    import lightning as L

    class Snapshot(L.Callback):
        def on_fit_start(self, trainer, system):
            self.start = {k: v.clone() for k, v in system.model.image_encoder.state_dict().items()}

        def on_train_end(self, trainer, system):
            self.end = system.model.image_encoder.state_dict()

    snapshot = Snapshot()
    train(tiny_config("trainer.max_epochs=2", "optim.freeze_encoder=true"), tmp_path / "run",
          extra_callbacks=[snapshot])
    stats = [k for k in snapshot.start if "running_" in k or "num_batches" in k]
    assert stats and all(torch.equal(snapshot.start[k], snapshot.end[k]) for k in snapshot.start)


def test_new_run_refuses_an_existing_run_folder(tmp_path, tiny_config):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("name: other\n", encoding="utf-8")
    with pytest.raises(FileExistsError, match="already holds a run that stopped before its "
                                              "first checkpoint; remove the folder"):
        train(tiny_config(), run)
    with pytest.raises(FileNotFoundError, match=r"nothing to resume.*stopped before its first"):
        train(tiny_config(), run, resume=True)
    # Checkpoints without a config (a folder of something else) are refused too.
    other = tmp_path / "other"
    (other / "checkpoints").mkdir(parents=True)
    (other / "checkpoints" / "last.ckpt").write_text("my notes", encoding="utf-8")
    with pytest.raises(FileExistsError, match="already holds checkpoints of a run"):
        train(tiny_config(), other)
    assert (other / "checkpoints" / "last.ckpt").read_text(encoding="utf-8") == "my notes"


def test_atomic_checkpoint_io_keeps_the_old_file_when_saving_fails(tmp_path):
    io = AtomicCheckpointIO()
    path = tmp_path / "last.ckpt"
    io.save_checkpoint({"step": 1}, path)

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        io.save_checkpoint({"step": 2, "bad": Unpicklable()}, path)
    assert io.load_checkpoint(path) == {"step": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]


def test_mixed_precision_run_keeps_a_float32_loss(tmp_path, tiny_config):
    # bf16 autocast is what CPUs offer; on GPUs the configs use 16-mixed the same way.
    config = tiny_config("trainer.precision=bf16-mixed", "trainer.max_epochs=1")
    run = train(config, tmp_path / "run")
    losses = [r["loss"] for r in read_history(run / "history" / "rank0.jsonl").values()]
    assert len(losses) == 4 and all(math.isfinite(v) and v > 0 for v in losses)
    state = torch.load(run / "model.pt", weights_only=True)["state_dict"]
    assert all(v.dtype == torch.float32 for v in state.values() if v.is_floating_point())


def test_the_system_passes_the_batch_no_target_flags_to_the_network():
    from tests.models.conftest import make_inputs

    torch.manual_seed(0)
    select = DeltarSystem("deltar-select", {"design_size": [64, 96]}, OptimConfig(lr=1e-2))
    select.eval()
    image, hypotheses, rects, valid = make_inputs(batch=2, height=64, width=96)
    valid = valid.clone()
    valid[:, :16] = False
    hypotheses = hypotheses * valid[..., None]
    batch = {"image": image, "hypotheses": hypotheses, "zone_rects": rects, "zone_valid": valid}
    with torch.no_grad():
        without = select(batch)["depth"]  # a batch from a reader without the flags
        flagged = select({**batch, "zone_no_target": ~valid})["depth"]
        direct = select.model(image, hypotheses, rects, valid, zone_no_target=~valid)["depth"]
    torch.testing.assert_close(flagged, direct)
    assert (flagged - without).abs().max() > 0.1


def test_format_2_training_checkpoints_still_load(tmp_path):
    """Runs saved before format 3 recorded the flat options as "overrides"."""
    from deltar.models import create_model

    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96), n_bins=8)
    flat = model.network_config.flat_options()
    torch.save({"deltar_model": {"preset": "deltar-lite", "overrides": flat,
                                 "format_version": 2},
                "state_dict": {f"model.{k}": v for k, v in model.state_dict().items()}},
               tmp_path / "old.ckpt")
    restored = load_trained_model(str(tmp_path / "old.ckpt"))
    assert restored.network_config == model.network_config
    for name, tensor in model.state_dict().items():
        assert torch.equal(restored.state_dict()[name], tensor), name


def test_the_batch_targets_reach_the_network(rng):
    # A plane-select network reads every target a zone reported: a batch whose zones
    # report a second surface predicts otherwise than one without.
    torch.manual_seed(0)
    select = DeltarSystem("deltar-select", {"design_size": [64, 96]}, OptimConfig(lr=1e-2))
    batch = {"image": torch.from_numpy(rng.standard_normal((1, 3, 64, 96)).astype(np.float32)),
             "hypotheses": torch.full((1, 64, 16), 2.0),
             "zone_rects": torch.tensor([[[r * 8.0, c * 12.0, r * 8.0 + 8, c * 12.0 + 12]
                                          for r in range(8) for c in range(8)]]),
             "zone_valid": torch.ones(1, 64, dtype=torch.bool)}
    targets = torch.zeros(1, 64, 2, 2)
    targets[..., 0, 0], targets[..., 0, 1] = 2.0, 0.5
    targets[..., 1, 0], targets[..., 1, 1] = 4.0, 0.5
    with torch.no_grad():
        plain = select(batch)["depth"]
        both = select({**batch, "zone_targets": targets})["depth"]
    assert (both - plain).abs().max() > 0.1
