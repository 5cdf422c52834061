"""Inference preparation: folded batch norms and channels-last keep the outputs."""

from __future__ import annotations

import copy

import pytest
import torch
from timm.layers import Conv2dSame
from torch import nn

from deltar.models import create_model
from deltar.models.optimize import (
    SymmetricSameConv2d,
    fuse_conv_batch_norm,
    prepare_for_inference,
)


def _with_random_norm_statistics(model: nn.Module) -> nn.Module:
    """Give every batch norm non-trivial statistics, so folding has something to do."""
    generator = torch.Generator().manual_seed(3)
    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm) and module.running_mean is not None:
            channels = module.num_features
            module.running_mean.copy_(0.1 * torch.randn(channels, generator=generator))
            module.running_var.copy_(0.5 + torch.rand(channels, generator=generator))
            module.weight.data.copy_(0.8 + 0.4 * torch.rand(channels, generator=generator))
            module.bias.data.copy_(0.1 * torch.randn(channels, generator=generator))
    return model.eval()


@pytest.mark.parametrize("head", ["bins", "zone_prior"])
def test_folded_channels_last_model_gives_the_same_depth(head, network_inputs):
    torch.manual_seed(0)
    model = _with_random_norm_statistics(create_model("deltar-lite", head=head))
    if head == "zone_prior":  # a non-zero last layer, so the logits matter
        with torch.no_grad():
            model.head.logits_conv.weight.normal_(0.0, 0.1)
    fast = prepare_for_inference(copy.deepcopy(model), fold_encoder=True, channels_last=True)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fast.decoder.modules())
    # The encoder's TensorFlow-"same" convolutions no longer copy their input to pad it.
    assert not any(isinstance(m, Conv2dSame) for m in fast.modules())
    assert sum(isinstance(m, SymmetricSameConv2d) for m in fast.modules()) == 5
    inputs = network_inputs()
    with torch.inference_mode():
        reference = model(*inputs)
        optimized = fast(*inputs)
    for key in ("depth", "uncertainty", "bin_edges"):
        torch.testing.assert_close(optimized[key], reference[key], rtol=1e-4, atol=1e-5)


def test_fold_needs_eval_mode_and_counts_folds():
    block = nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.ReLU())
    with pytest.raises(ValueError, match="eval"):
        fuse_conv_batch_norm(block)
    _with_random_norm_statistics(block)
    x = torch.randn(2, 3, 8, 8)
    expected = block(x)
    assert fuse_conv_batch_norm(block) == 1
    assert isinstance(block[1], nn.Identity)
    torch.testing.assert_close(block(x), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("size", [(16, 20), (15, 20), (16, 19), (15, 17), (2, 3)])
@pytest.mark.parametrize(("kernel", "stride", "groups"), [(3, 2, 1), (3, 2, 8), (5, 2, 8),
                                                          (3, 1, 1), (4, 2, 2), (3, 3, 1)])
def test_symmetric_same_convolution_matches_timm(size, kernel, stride, groups):
    torch.manual_seed(0)
    same = Conv2dSame(8, 8, kernel, stride=stride, groups=groups, bias=True).eval()
    fast = SymmetricSameConv2d(copy.deepcopy(same)).eval()
    x = torch.randn(2, 8, *size)
    with torch.no_grad():
        expected = same(x)
        got = fast(x)
        layout = fast.to(memory_format=torch.channels_last)(
            x.contiguous(memory_format=torch.channels_last))
    assert got.shape == expected.shape
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(layout, expected, rtol=1e-5, atol=1e-6)


def test_symmetric_same_convolution_refuses_dilation():
    with pytest.raises(ValueError, match="dilation"):
        SymmetricSameConv2d(Conv2dSame(4, 4, 3, stride=2, dilation=2))


def test_symmetric_same_convolution_per_axis_and_in_half_precision():
    torch.manual_seed(1)
    same = Conv2dSame(6, 4, (3, 5), stride=(1, 2), bias=False).eval()
    fast = SymmetricSameConv2d(same).eval()
    x = torch.randn(1, 6, 9, 14)
    with torch.no_grad():
        torch.testing.assert_close(fast(x), same(x), rtol=1e-5, atol=1e-6)
        half = x.to(torch.bfloat16)
        same_half = copy.deepcopy(same).to(torch.bfloat16)
        torch.testing.assert_close(SymmetricSameConv2d(same_half)(half), same_half(half),
                                   rtol=2e-2, atol=2e-2)
    # The rewrite shares the parameters: the same state dict, both ways.
    assert fast.state_dict().keys() == same.state_dict().keys()
    assert fast.weight is same.weight
