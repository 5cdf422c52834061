"""``deltar check-official`` and ``deltar bench`` end to end (small inputs)."""

from __future__ import annotations

import json

import pytest
import torch
from typer.testing import CliRunner

from deltar.cli.main import app
from tests.models.rounding import ratio_bounds


@pytest.fixture(scope="module")
def runner():
    return CliRunner()


@pytest.fixture(scope="module")
def one_case_fixture(parity_fixture):
    return {**parity_fixture, "cases": parity_fixture["cases"][:1]}


def test_check_official_passes_and_fails(runner, one_case_fixture, tmp_path):
    good = tmp_path / "good.pt"
    torch.save(one_case_fixture, good)
    result = runner.invoke(app, ["check-official", str(good)])
    assert result.exit_code == 0, result.output
    assert "pass" in result.output
    assert "what this checks: the network on the release's own inputs" in result.output

    shifted = dict(one_case_fixture)
    case = dict(shifted["cases"][0])
    case["expected_depth_half_res"] = case["expected_depth_half_res"] + 0.01
    shifted["cases"] = [case]
    bad = tmp_path / "bad.pt"
    torch.save(shifted, bad)
    result = runner.invoke(app, ["check-official", str(bad)])
    assert result.exit_code == 1
    assert "FAIL" in result.output


def test_check_official_missing_file(runner, tmp_path):
    result = runner.invoke(app, ["check-official", str(tmp_path / "none.pt")])
    assert result.exit_code == 2
    assert f"Invalid value for FIXTURE: fixture not found: {tmp_path / 'none.pt'}" in result.stderr


def test_bench_writes_json(runner, tmp_path):
    out = tmp_path / "bench.json"
    args = ["bench", "--preset", "deltar-lite", "--size", "64x96", "--repeats", "1",
            "--warmup", "0", "--threads", "1", "--matmul-size", "128", "--json", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    for key in ("preset", "size", "batch", "threads", "latency_ms_median", "latency_ms_min",
                "peak_mem_mb", "params_m", "gflop", "gflop_s", "matmul_gflop_s",
                "matmul_fraction"):
        assert key in data
    assert data["size"] == "64x96" and data["latency_ms_median"] > 0
    assert data["gflop"] > 0 and data["matmul_gflop_s"] > 0
    # The JSON rounds gflop_s to 0.01, matmul_gflop_s to 0.1 and the fraction to 0.001;
    # the fraction must lie within what those roundings allow.
    low, high = ratio_bounds(data["gflop_s"], 0.01, data["matmul_gflop_s"], 0.1, 1e-3)
    assert low <= data["matmul_fraction"] <= high
    # Never overwrite without being asked.
    again = runner.invoke(app, args)
    assert again.exit_code == 1  # as every command's existing output
    assert f"--json {out} exists; pass --overwrite to replace it" in again.stderr


def test_bench_rejects_bad_size(runner):
    result = runner.invoke(app, ["bench", "--size", "100x100"])
    assert result.exit_code == 2
    assert ("Invalid value for --size: needs positive multiples of 32, got '100x100'"
            in result.stderr)


def test_bench_channels_last_and_encoder_folding_are_reported(runner, tmp_path):
    out = tmp_path / "bench.json"
    result = runner.invoke(app, ["bench", "--preset", "deltar-lite", "--size", "64x96",
                                 "--repeats", "1", "--warmup", "0", "--threads", "1",
                                 "--channels-last", "--no-fold-encoder", "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["channels_last"] is True and data["encoder_folded"] is False
