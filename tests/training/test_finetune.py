"""Fine-tuning on ZJU-L5-layout data from earlier weights (the CLI: tests/cli/test_train.py)."""

from __future__ import annotations

import numpy as np
import torch

from deltar.data.zju_l5 import ZJUL5Sample, write_zju_l5
from deltar.models import create_model
from deltar.training.module import export_model
from deltar.training.run import build_system, read_history, train

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
