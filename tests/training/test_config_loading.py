"""Reading the training configuration: shipped files round trip, unknown keys named,
``key=value`` overrides, missing and corrupt files."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from deltar.training.config_loading import apply_override, config_from_dict, load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _minimal() -> dict:
    return {"data": {"sources": [{"kind": "procedural", "frames": 4}]}}


@pytest.mark.parametrize("name", ["nyu_official", "cross_scene_lite", "cross_scene_select",
                                  "zju_finetune", "tiny_test"])
def test_shipped_configs_load_and_round_trip(name):
    config = load_config(CONFIGS / f"{name}.yaml")
    again = config_from_dict(yaml.safe_load(config.to_yaml()))
    assert again.to_dict() == config.to_dict()


@pytest.mark.parametrize(("data", "named"), [
    ({"optimm": {}}, "optimm"),
    ({"optim": {"lrr": 1}}, "optim.lrr"),
    ({"data": {"sources": [{"kind": "procedural", "frames": 4, "pth": "x"}]}},
     "data.sources.0.pth"),
])
def test_unknown_keys_are_named(data, named):
    merged = {**_minimal(), **data}
    with pytest.raises(ValueError, match=named.replace(".", r"\.")):
        config_from_dict(merged)


def test_overrides_parse_yaml_values_and_list_indices(tmp_path):
    config = load_config(CONFIGS / "tiny_test.yaml", [
        "optim.lr=1e-4", "data.sources.0.frames=7", "data.image_augmentation.crop=[32, 64]",
        "model.overrides.n_bins=8", "trainer.limit_val_batches=0.5", "trainer.devices=auto"])
    assert config.optim.lr == pytest.approx(1e-4) and isinstance(config.optim.lr, float)
    assert config.data.sources[0].frames == 7
    assert config.data.image_augmentation.crop == [32, 64]
    assert config.model.overrides["n_bins"] == 8
    assert config.trainer.limit_val_batches == 0.5
    assert config.trainer.devices == "auto"


@pytest.mark.parametrize("override", ["optim.lr", "=3", "data.sources.5.path=x"])
def test_malformed_overrides_raise(override):
    with pytest.raises(ValueError, match="override"):
        apply_override(_minimal(), override)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.yaml"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("optim: [unclosed\n", encoding="utf-8")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_config(bad)


def test_unreadable_configs_name_the_file(tmp_path):
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 50_000 + "]" * 50_000 + "\n")
    with pytest.raises(ValueError, match=r"deep\.yaml: cannot read training config: "):
        load_config(deep)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(ValueError, match=r"binary\.yaml: cannot read training config: not "
                       r"UTF-8 text \(byte 0xff at position 0\)$"):
        load_config(binary)
    with pytest.raises(IsADirectoryError, match=f"^training config {tmp_path} is a folder, "
                       "not a file$"):
        load_config(tmp_path)
    odd = tmp_path / "odd.yaml"
    odd.write_text("trainer: 5\n")
    with pytest.raises(ValueError, match=r"^training config .*odd\.yaml: "):
        load_config(odd)
