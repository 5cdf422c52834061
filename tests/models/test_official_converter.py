"""Official state-dict conversion: names, wrappers, reports, file errors."""

from __future__ import annotations

import pytest
import torch

from deltar.models import create_model, load_official_weights
from deltar.models.official import official_to_ours, unwrap_state_dict


@pytest.fixture(scope="module")
def official_state(parity_fixture):
    return parity_fixture["state_dict"]


@pytest.fixture(scope="module")
def model():
    return create_model("deltar-official")


@pytest.mark.parametrize(
    ("official", "ours"),
    [
        ("img_encoder.conv0.0.weight", "image_encoder.backbone.conv_stem.weight"),
        ("img_encoder.conv3.1.0.conv_pw.weight",
         "image_encoder.backbone.blocks.4.0.conv_pw.weight"),
        ("hist_encoder.hist_extractor2.pointnet_encoder.bn3.running_var",
         "distribution_encoder.blocks.1.mlp.7.running_var"),
        ("decoder.cross_atten1.layers.1.gsa.sr.weight",
         "decoder.fusions.2.layers.1.global_.reduce.weight"),
        ("decoder.cross_atten3.layers.0.merge.weight",
         "decoder.fusions.0.layers.0.out_proj.weight"),
        ("decoder.up4._net.3.bias", "decoder.up_blocks.3.block.3.bias"),
        ("conv_out.0.bias", "head.logits_conv.bias"),
        ("something.else", None),
    ],
)
def test_name_rules(official, ours):
    assert official_to_ours(official) == ours


def test_every_fixture_key_loads_and_values_arrive(model, official_state):
    report = load_official_weights(model, official_state)
    assert report.ok and report.loaded == len(official_state)
    ours = model.state_dict()
    torch.testing.assert_close(
        ours["head.logits_conv.weight"], official_state["conv_out.0.weight"].float()
    )
    # The flat (H * W, C) positional encoding arrives as an (H, W, C) grid, row-major.
    flat = official_state["decoder.cross_atten2.positional_encodings"].float()
    grid = ours["decoder.fusions.1.image_position"]
    torch.testing.assert_close(grid[1, 2], flat[1 * grid.shape[1] + 2])


def test_wrapped_and_prefixed_checkpoints(model, official_state):
    wrapped = {"model": {f"module.{key}": value for key, value in official_state.items()}}
    assert unwrap_state_dict(wrapped).keys() == official_state.keys()
    assert load_official_weights(model, wrapped).ok


def test_unmapped_and_missing_keys_are_reported(model, official_state):
    partial = dict(list(official_state.items())[:-2])
    partial["extra.head.weight"] = torch.zeros(3)
    with pytest.raises(ValueError, match="unmapped"):
        load_official_weights(model, partial)
    report = load_official_weights(model, partial, strict=False)
    assert report.unmapped == ["extra.head.weight"]
    assert len(report.missing) == 2 and not report.ok


def test_file_errors(model, tmp_path):
    with pytest.raises(FileNotFoundError):
        load_official_weights(model, tmp_path / "nyu.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"corrupt\.pt"):
        load_official_weights(model, corrupt)
