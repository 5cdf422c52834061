"""Packaging a run's network as a small (float16) deltar checkpoint."""

from __future__ import annotations

import pytest
import torch

from deltar.models import create_model
from deltar.models.checkpoint import load_checkpoint
from deltar.training.module import export_model
from deltar.training.package import package_checkpoint

TINY = {"decoder_channels": (32, 32, 16, 16, 8), "head_channels": 16, "n_bins": 16,
        "design_size": (64, 96), "head": "zone_prior"}


def _inputs():
    generator = torch.Generator().manual_seed(0)
    image = torch.randn(1, 3, 64, 96, generator=generator)
    rects = torch.tensor([[[r * 16.0, c * 24.0, r * 16.0 + 16, c * 24.0 + 24]
                           for r in range(4) for c in range(4)]])
    hypotheses = (torch.rand(1, 16, 1, generator=generator) * 3 + 0.5).expand(1, 16, 16)
    return image, hypotheses.contiguous(), rects, torch.ones(1, 16, dtype=torch.bool)


def test_float16_package_loads_and_predicts_like_the_original(tmp_path):
    torch.manual_seed(0)
    model = create_model("deltar-lite", **TINY).eval()
    with torch.no_grad():  # non-trivial head weights, so the comparison means something
        model.head.logits_conv.weight.normal_(0, 0.1)
    source = tmp_path / "model.pt"
    torch.save(export_model(model, "deltar-lite"), source)
    packed = package_checkpoint(source, tmp_path / "small.pt")
    assert packed.stat().st_size < 0.6 * source.stat().st_size
    loaded, preset, config = load_checkpoint(packed)
    assert preset == "deltar-lite" and config["head"]["name"] == "zone_prior"
    with torch.no_grad():
        expected = model(*_inputs())["depth"]
        actual = loaded(*_inputs())["depth"]
    assert next(loaded.parameters()).dtype == torch.float32
    torch.testing.assert_close(actual, expected, rtol=2e-2, atol=1e-2)


def test_package_never_overwrites(tmp_path):
    model = create_model("deltar-lite", **TINY)
    source = tmp_path / "model.pt"
    torch.save(export_model(model, "deltar-lite"), source)
    with pytest.raises(ValueError, match="source"):
        package_checkpoint(source, source)
    package_checkpoint(source, tmp_path / "small.pt")
    with pytest.raises(FileExistsError):
        package_checkpoint(source, tmp_path / "small.pt")
