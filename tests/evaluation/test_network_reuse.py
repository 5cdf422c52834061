"""Reusing the network's outputs within an output-stage fit: same numbers, fewer runs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import deltar.evaluation.uncertainty as uncertainty_module
from deltar.evaluation.network_reuse import (
    NetworkStore,
    network_input_key,
    reuse_network_outputs,
)
from deltar.evaluation.uncertainty import fit_checkpoint_uncertainty
from deltar.models import create_model
from deltar.models.checkpoint import load_checkpoint, save_checkpoint
from tests.evaluation.test_uncertainty import _far_sample


def _inputs(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"image": rng.normal(size=(1, 3, 8, 8)).astype(np.float32),
            "hypotheses": rng.uniform(1, 3, (1, 16, 4)).astype(np.float32),
            "zone_rects": np.zeros((1, 16, 4), np.float32),
            "zone_valid": np.ones((1, 16), bool), "zone_no_target": None,
            "network_size": (8, 8)}


def test_the_store_runs_each_input_once_and_hands_out_copies():
    calls = []

    def run(inputs):
        calls.append(1)
        value = float(inputs["image"].sum())
        return np.full((1, 1, 4, 4), value, np.float32), np.ones((1, 1, 4, 4), np.float32)

    setting = ["a"]
    store = NetworkStore(run, configuration=lambda: setting[0])
    first, _ = store(_inputs(0))
    first += 100.0  # the caller's copy: the stored outputs stay as they were
    again, _ = store(_inputs(0))
    assert len(calls) == 1 and (store.hits, store.misses) == (1, 1)
    np.testing.assert_array_equal(again, run(_inputs(0))[0])
    changed = _inputs(0)
    changed["zone_valid"][0, 3] = False
    store(changed)
    setting[0] = "b"  # another network configuration: run again
    store(_inputs(0))
    assert store.misses == 3
    # The key reads every network input, its dtype and shape, not the other entries.
    assert network_input_key(_inputs(0)) != network_input_key(_inputs(1))
    other = _inputs(0)
    other["network_size"] = (16, 16)
    assert network_input_key(other) == network_input_key(_inputs(0))
    wider = _inputs(0)
    wider["zone_valid"] = wider["zone_valid"].astype(np.uint8)
    assert network_input_key(wider) != network_input_key(_inputs(0))
    # Beyond the budget the least recently used outputs go first.
    small = NetworkStore(run, budget_bytes=2 * 128)
    for seed in (0, 1, 2):
        small(_inputs(seed))
    small(_inputs(0))
    assert small.misses == 4
    with pytest.raises(ValueError, match="budget_bytes"):
        NetworkStore(run, budget_bytes=-1)


def test_a_fit_with_the_store_equals_one_without_it(tmp_path, monkeypatch):
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    source = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    # Frames with no-target zones: the fit moves the network's no-target depth, which
    # the store must tell apart.
    sets = [[_far_sample(seed, 6.0) for seed in range(3)]]
    stores = []

    def counted(estimator, *args, **kwargs):
        stores.append(reuse_network_outputs(estimator, *args, **kwargs))
        return stores[-1]

    monkeypatch.setattr(uncertainty_module, "reuse_network_outputs", counted)
    with_store = fit_checkpoint_uncertainty(source, sets, tmp_path / "a.pt", min_pixels=100)
    monkeypatch.setattr(uncertainty_module, "reuse_network_outputs", lambda estimator: None)
    without = fit_checkpoint_uncertainty(source, sets, tmp_path / "b.pt", min_pixels=100)
    assert load_checkpoint(with_store.path)[2] == load_checkpoint(without.path)[2]
    assert with_store.no_target_depth_m == 6.0 == without.no_target_depth_m
    assert with_store.no_target_depth_errors == without.no_target_depth_errors
    assert with_store.zone_consistency_errors == without.zone_consistency_errors
    # At least the zone-consistency strengths and the pixel collection repeat the
    # network's inputs: three frames, four passes alike, one run each.
    assert stores[0].hits >= 9 and stores[0].misses > 0
