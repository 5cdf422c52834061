"""Image encoder: fewer levels cut the backbone without changing the maps it returns."""

from __future__ import annotations

import pytest
import torch

from deltar.models import create_model
from deltar.models.encoders import ImageEncoder


@pytest.fixture(scope="module")
def full_and_cut():
    torch.manual_seed(0)
    full = ImageEncoder("tf_efficientnet_lite0").eval()
    cut = ImageEncoder("tf_efficientnet_lite0", levels=4).eval()
    return full, cut


def test_fewer_levels_remove_the_unused_blocks(full_and_cut):
    full, cut = full_and_cut
    assert len(full.backbone.blocks) == 7 and len(cut.backbone.blocks) == 5
    assert cut.channels == full.channels[:4] == (16, 24, 40, 112)
    # The stride-32 stages hold most of Lite0's weights.
    def count(module):
        return sum(p.numel() for p in module.parameters())

    assert count(cut) < 0.3 * count(full)


def test_a_whole_backbone_state_dict_loads_strictly_and_gives_the_same_maps(full_and_cut):
    full, cut = full_and_cut
    cut.load_state_dict(full.state_dict(), strict=True)
    image = torch.randn(1, 3, 64, 96, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        expected, got = full(image), cut(image)
    assert len(got) == 4
    for reference, maps in zip(expected[:4], got, strict=True):
        torch.testing.assert_close(maps, reference, rtol=0, atol=0)


def test_other_unexpected_keys_still_fail(full_and_cut):
    full, cut = full_and_cut
    state = full.state_dict()
    state["backbone.conv_head.weight"] = torch.zeros(1)
    with pytest.raises(RuntimeError, match="conv_head"):
        cut.load_state_dict(state, strict=True)
    missing = dict(full.state_dict())
    missing.pop("backbone.blocks.4.0.conv_pw.weight")
    with pytest.raises(RuntimeError, match=r"blocks\.4\.0\.conv_pw"):
        cut.load_state_dict(missing, strict=True)


@pytest.mark.parametrize("levels", [0, 6, 2.5, True])
def test_levels_are_checked(levels):
    with pytest.raises(ValueError, match=r"levels must be an integer in 1\.\.5"):
        ImageEncoder("tf_efficientnet_lite0", levels=levels)


def test_a_backbone_timm_cuts_itself_also_loads_whole_weights():
    # timm builds a ResNet without the layers past the last map asked for; weights
    # saved with them load strictly, and only those tensors are skipped.
    torch.manual_seed(0)
    whole = ImageEncoder("resnet18").eval()
    cut = ImageEncoder("resnet18", levels=4).eval()
    assert not any(k.startswith("backbone.layer4.") for k in cut.state_dict())
    cut.load_state_dict(whole.state_dict(), strict=True)
    image = torch.randn(1, 3, 64, 96, generator=torch.Generator().manual_seed(2))
    with torch.inference_mode():
        for reference, maps in zip(whole(image)[:4], cut(image), strict=True):
            torch.testing.assert_close(maps, reference, rtol=0, atol=0)


def test_descriptor_network_runs_only_the_strides_it_reads():
    torch.manual_seed(0)
    coarse = create_model("deltar-select", descriptor_strides=(8, 32))
    fine = create_model("deltar-select", descriptor_strides=(8, 16))
    assert len(coarse.image_encoder.channels) == 5
    assert len(fine.image_encoder.channels) == 4
    # Weights of the longer encoder load into the shorter one (older checkpoints).
    state = {k: v for k, v in coarse.state_dict().items() if not k.startswith("decoder.")}
    state.update({k: v for k, v in fine.state_dict().items() if k.startswith("decoder.")})
    fine.load_state_dict(state, strict=True)
