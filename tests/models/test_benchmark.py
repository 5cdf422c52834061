"""FLOP counting and the matmul reference of ``deltar.models.benchmark`` (small sizes)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from deltar.models import create_model
from deltar.models.benchmark import (
    benchmark_preset,
    count_gflop,
    matmul_gflop_s,
    synthetic_inputs,
)
from tests.models.rounding import ratio_bounds


def test_count_gflop_of_a_convolution_matches_the_formula():
    conv = nn.Conv2d(3, 8, kernel_size=3, padding=1).eval()
    gflop = count_gflop(conv, (torch.zeros(2, 3, 32, 32),))
    # 2 FLOP per multiply-add: batch * out * in * k * k * H * W.
    assert gflop * 1e9 == pytest.approx(2 * 2 * 8 * 3 * 9 * 32 * 32)


def test_gflop_grows_with_the_input_size():
    torch.manual_seed(0)
    model = create_model("deltar-lite").eval()
    small = count_gflop(model, synthetic_inputs(64, 96, 1))
    large = count_gflop(model, synthetic_inputs(128, 192, 1))
    batch = count_gflop(model, synthetic_inputs(64, 96, 2))
    # Four times the pixels: the convolutions scale by 4, the per-zone parts do not.
    assert 2.5 < large / small <= 4.0 + 1e-6
    assert batch / small == pytest.approx(2.0, rel=1e-6)


def test_matmul_rate_is_positive_and_checks_arguments():
    assert matmul_gflop_s(64, repeats=1) > 0
    with pytest.raises(ValueError, match="size"):
        matmul_gflop_s(0)


def test_benchmark_reports_flops_and_fraction_with_overrides():
    result = benchmark_preset("deltar-lite", 64, 96, threads=1, repeats=1, warmup=0,
                              matmul_size=128, overrides={"n_bins": 32})
    assert result["overrides"] == {"n_bins": 32}
    assert result["gflop"] > 0
    # gflop is rounded to 0.001 and the latency to 0.1 ms: the rate must lie within what
    # those roundings allow (a fast machine runs this small input in a few ms).
    low, high = ratio_bounds(result["gflop"], 1e-3, result["latency_ms_min"] / 1e3, 1e-4,
                             0.01)
    assert low <= result["gflop_s"] <= high
    # The fraction is the reported gflop_s over the unrounded reference rate, rounded to
    # three decimals; the reported reference is rounded to 0.1 (slow at this small size,
    # where its rounding counts).
    low, high = ratio_bounds(result["gflop_s"], 0.0, result["matmul_gflop_s"], 0.1, 1e-3)
    assert 0 < result["matmul_fraction"] and low <= result["matmul_fraction"] <= high
    skipped = benchmark_preset("deltar-lite", 64, 96, threads=1, repeats=1, warmup=0,
                               matmul_size=0)
    assert skipped["matmul_gflop_s"] is None and skipped["matmul_fraction"] is None
    with pytest.raises(ValueError, match="matmul_size"):
        benchmark_preset("deltar-lite", 64, 96, matmul_size=-1)
