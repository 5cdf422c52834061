"""The training configuration's schema: each section's value checks and the shipped
recipes' values."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from deltar.training.config_loading import apply_override, config_from_dict, load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _minimal() -> dict:
    return {"data": {"sources": [{"kind": "procedural", "frames": 4}]}}


def test_nyu_official_matches_the_release_recipe():
    # Values from reference/paper_and_release.md ("Release training config").
    c = load_config(CONFIGS / "nyu_official.yaml")
    assert c.model.preset == "deltar-official"
    assert c.data.image_augmentation.crop == [416, 544]
    assert c.data.image_augmentation.max_rotation_deg == 2.5
    assert c.data.batch_size == 16 and c.trainer.max_epochs == 25
    assert (c.data.zone_layout, c.data.training_grid, c.data.training_zone_px) == (
        "training", 6, 64)
    sig = c.data.signal_augmentation
    assert (sig.drop_fraction, sig.noise_prob, sig.noise_mean_m, sig.noise_std_m) == (
        0.34, 0.3, 0.17, 0.20)
    # Trained on uniform hypotheses, tested (the checkpoint's contract) on inverse-CDF ones.
    assert c.data.sampling == "uniform" and c.model.overrides["hypothesis_sampling"] == "icdf"
    o = c.optim
    assert (o.lr, o.weight_decay, o.div_factor, o.final_div_factor) == (3e-4, 0.1, 25, 100)
    assert o.encoder_lr_factor == 0.1
    assert (o.loss_alpha, o.loss_lambda) == (10.0, 0.85)


@pytest.mark.parametrize(("override", "message"), [
    ("optim.lr=fast", "optim.lr must be a number"),
    ("optim.lr=-1", "optim.lr must be > 0"),
    ("trainer.strategy=horovod", "trainer.strategy"),
    ("data.batch_size=2.5", "data.batch_size must be an integer"),
    ("data.image_augmentation.crop=[100, 128]", "multiple of 32"),
    ("data.sources.0.holdout_fraction=1.0", "holdout_fraction"),
    ("data.sources.0.role=val", "no source has role 'train'"),
    ("data.zone_layout=diagonal", "data.zone_layout"),
    ("data.max_targets=5", "data.max_targets must be 1, 2, 3 or 4"),
    ("data.sources.0.seed=-1", r"data.sources.0.seed must be >= 0, got -1"),
    ("model.preset=bogus", "model.preset must be one of .*deltar-select.*got 'bogus'"),
])
def test_invalid_values_raise_naming_the_key(override, message):
    data = _minimal()
    apply_override(data, override)
    with pytest.raises(ValueError, match=message):
        config_from_dict(data)


def test_new_recipe_keys_are_checked():
    base = load_config(CONFIGS / "cross_scene_lite.yaml").to_dict()
    assert base["model"]["encoder_weights"] == "imagenet"
    assert base["data"]["depth_scale_range"] == [0.5, 2.0]
    for dotted, value, message in (
            ("data.depth_scale_range", [2.0, 1.0], "depth_scale_range"),
            ("data.layout_jitter_px", -1.0, "layout_jitter_px"),
            ("data.image_augmentation.max_zoom", 0.5, "max_zoom"),
            ("data.sources.0.every", 0, "every")):
        config = yaml.safe_load(yaml.safe_dump(base))
        apply_override(config, f"{dotted}={value}")
        with pytest.raises(ValueError, match=message):
            config_from_dict(config)
