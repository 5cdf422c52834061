"""Inference preparation: folded batch norms and channels-last keep the outputs."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from deltar.models import create_model
from deltar.models.optimize import fuse_conv_batch_norm, prepare_for_inference


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
