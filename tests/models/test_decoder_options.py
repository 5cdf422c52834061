"""CPU shapes of the decoder: separable units, fewer convolutions, a 1x1 output conv."""

from __future__ import annotations

import copy

import pytest
import torch

from deltar.models import create_model
from deltar.models.benchmark import count_gflop, synthetic_inputs
from deltar.models.decoder import FusionDecoder, UpBlock
from deltar.models.optimize import prepare_for_inference

CPU_SHAPE = {"decoder_block": "separable", "decoder_convs": (2, 2, 1, 1),
             "decoder_out_kernel": 1}


def test_defaults_keep_the_release_decoder():
    model = create_model("deltar-official")
    block = model.decoder.up_blocks[0].block
    # conv, BN, act, conv, BN, act: the layout the official weights map onto.
    assert [type(m).__name__ for m in block] == ["Conv2d", "BatchNorm2d", "LeakyReLU"] * 2
    assert block[0].kernel_size == (3, 3) and block[0].groups == 1
    assert model.decoder.out_conv.kernel_size == (3, 3)
    assert model.config["decoder_block"] == "conv"
    assert model.config["decoder_convs"] == (2, 2, 2, 2)


def test_cpu_shape_runs_costs_less_and_folds_exactly():
    torch.manual_seed(0)
    base = create_model("deltar-lite").eval()
    torch.manual_seed(0)
    shaped = create_model("deltar-lite", **CPU_SHAPE).eval()
    inputs = synthetic_inputs(64, 96, 2)
    assert count_gflop(shaped, inputs) < 0.8 * count_gflop(base, inputs)
    block = shaped.decoder.up_blocks[3].block
    assert block[0].groups == block[0].in_channels and len(block) == 4  # one unit
    assert shaped.decoder.out_conv.kernel_size == (1, 1)
    # Give the batch norms non-trivial statistics, then check folding keeps the output.
    for module in shaped.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.2, 0.2)
            module.running_var.uniform_(0.5, 1.5)
    with torch.inference_mode():
        plain = shaped(*inputs)["depth"]
        folded = prepare_for_inference(copy.deepcopy(shaped))(*inputs)["depth"]
    assert torch.isfinite(plain).all()
    torch.testing.assert_close(folded, plain, rtol=1e-4, atol=1e-4)


def test_cpu_shape_is_recorded_and_rebuilds_from_the_config():
    model = create_model("deltar-lite", **CPU_SHAPE)
    again = create_model("deltar-lite", **{key: model.config[key] for key in CPU_SHAPE})
    assert again.load_state_dict(model.state_dict()) is not None


@pytest.mark.parametrize("kwargs, message", [
    ({"block": "winograd"}, "decoder block"),
    ({"convs": (2, 2, 2)}, "one count per up block"),
    ({"convs": (2, 2, 2, 0)}, "at least one"),
    ({"out_kernel": 5}, "out_kernel"),
])
def test_bad_decoder_options_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FusionDecoder((16, 24, 40, 112, 160), **kwargs)


def test_up_block_separable_output_shape():
    block = UpBlock(24, 8, block="separable", convs=2).eval()
    out = block(torch.randn(1, 16, 4, 6), torch.randn(1, 8, 8, 12))
    assert out.shape == (1, 8, 8, 12)
