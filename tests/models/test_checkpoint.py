"""The deltar checkpoint carries the weights' input contract; format 2 files are read,
other versions are refused."""

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
    assert preset == "deltar-lite" and config == model.config()
    assert torch.load(path, weights_only=True)["format_version"] == 3
    for key, value in {"image_mean": (0.5, 0.5, 0.5), "image_std": (0.5, 0.5, 0.5),
                       "design_size": (64, 96), "hypothesis_sampling": "uniform",
                       "num_hypotheses": 8, "zone_scale_norm": True}.items():
        assert config["input"][key] == value, key
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
    payload["config"]["head"]["n_bins"] = 7
    torch.save(payload, wrong)
    with pytest.raises(ValueError, match=r"wrong\.pt: weights do not fit"):
        load_checkpoint(wrong)


def test_format_2_files_load_with_the_same_weights_and_outputs(tmp_path):
    """Format 2 stored the options flat; the state-dict keys are the same."""
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96), head="zone_select").eval()
    flat = {k: list(v) if isinstance(v, tuple) else v
            for k, v in model.network_config.flat_options().items()}
    flat["bin_norm"] = "linear"  # a removed option at the only value it had
    payload = {**checkpoint_payload(model, "deltar-lite"), "format_version": 2,
               "config": flat}
    torch.save(payload, tmp_path / "v2.pt")
    restored, preset, config = load_checkpoint(tmp_path / "v2.pt")
    assert preset == "deltar-lite" and config == model.config()
    rects = torch.tensor([[0.0, 0.0, 32.0, 48.0], [0.0, 48.0, 32.0, 96.0],
                          [32.0, 0.0, 64.0, 48.0], [32.0, 48.0, 64.0, 96.0]])[None]
    inputs = (torch.rand(1, 3, 64, 96), torch.rand(1, 4, 16) + 1, rects,
              torch.ones(1, 4, dtype=torch.bool))
    with torch.no_grad():
        torch.testing.assert_close(restored(*inputs)["depth"], model(*inputs)["depth"])
    payload["config"] = {**flat, "bin_norm": "log"}
    torch.save(payload, tmp_path / "removed.pt")
    with pytest.raises(ValueError, match="bin_norm"):
        load_checkpoint(tmp_path / "removed.pt")

