"""The deltar checkpoint carries the weights' input contract; other versions are refused."""

from __future__ import annotations

import pytest
import torch

from deltar.models import create_model
from deltar.models.checkpoint import (
    CHECKPOINT_FORMAT,
    checkpoint_payload,
    load_checkpoint,
    save_checkpoint,
)


def test_round_trip_keeps_the_input_contract(tmp_path):
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96), hypothesis_sampling="uniform",
                         num_hypotheses=8)
    path = save_checkpoint(tmp_path / "m.pt", model, "deltar-lite")
    restored, preset, config = load_checkpoint(path)
    assert preset == "deltar-lite" and config == model.config
    for key, value in {"image_mean": (0.5, 0.5, 0.5), "image_std": (0.5, 0.5, 0.5),
                       "design_size": (64, 96), "hypothesis_sampling": "uniform",
                       "num_hypotheses": 8, "zone_scale_norm": True}.items():
        assert config[key] == value, key
    for name, tensor in model.state_dict().items():
        assert torch.equal(restored.state_dict()[name], tensor), name


def test_version_1_files_are_refused(tmp_path):
    model = create_model("deltar-lite", design_size=(64, 96))
    path = tmp_path / "v1.pt"
    torch.save({**checkpoint_payload(model, "deltar-lite"), "format_version": 1}, path)
    with pytest.raises(ValueError, match=r"v1\.pt.*format_version 1"):
        load_checkpoint(path)


def test_foreign_and_future_files_are_refused(tmp_path):
    model = create_model("deltar-lite", design_size=(64, 96))
    future = tmp_path / "future.pt"
    torch.save({**checkpoint_payload(model, "deltar-lite"), "format_version": 99}, future)
    with pytest.raises(ValueError, match=r"future\.pt.*format_version 99"):
        load_checkpoint(future)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": 1}, foreign)
    with pytest.raises(ValueError, match=rf"foreign\.pt.*{CHECKPOINT_FORMAT}"):
        load_checkpoint(foreign)
    wrong = tmp_path / "wrong.pt"
    payload = checkpoint_payload(model, "deltar-lite")
    payload["config"] = {**payload["config"], "n_bins": 7}
    torch.save(payload, wrong)
    with pytest.raises(ValueError, match=r"wrong\.pt: weights do not fit"):
        load_checkpoint(wrong)
