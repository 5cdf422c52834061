"""Tests of the numpy hypothesis sampling (deltar.sensor.hypotheses) the estimator uses:
equal to the PyTorch sampling of training (deltar.sensor.sampling) within float32
rounding, and to the release's own samples."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.sensor.hypotheses import zone_hypotheses, zone_hypotheses_from_histogram
from deltar.sensor.sampling import sample_hypotheses, sample_hypotheses_from_histogram


def test_reproduces_the_official_icdf_samples(parity_fixture):
    for case in parity_fixture["cases"]:
        mean_sigma = case["zone_mean_sigma_m"].numpy()
        samples = zone_hypotheses(mean_sigma[:, 0], mean_sigma[:, 1],
                                  case["zone_valid"].numpy(), 16, "icdf")
        assert samples.shape == (64, 16) and samples.dtype == np.float32
        np.testing.assert_allclose(samples, case["zone_samples_icdf16"].numpy(), atol=1e-5,
                                   rtol=0, err_msg=case["name"])


@pytest.mark.parametrize("method", ["icdf", "uniform"])
def test_equals_the_torch_sampling(rng, method):
    mean = rng.uniform(0.05, 4.0, size=(2, 64)).astype(np.float32)
    sigma = rng.uniform(0.0, 0.6, size=(2, 64)).astype(np.float32)  # some go below 0 m
    valid = rng.random((2, 64)) > 0.2
    mean[~valid] = np.nan  # garbage in invalid zones is ignored by both
    ours = zone_hypotheses(mean, sigma, valid, 16, method)
    theirs = sample_hypotheses(torch.from_numpy(mean), torch.from_numpy(sigma),
                               torch.from_numpy(valid), 16, method).numpy()
    assert ours.shape == theirs.shape == (2, 64, 16)
    # torch computes the quantiles in float32, here in float64: a few micrometres apart.
    np.testing.assert_allclose(ours, theirs, atol=1e-5, rtol=0)
    assert np.all(ours[~valid] == 0) and np.all(ours >= 0)


def test_histogram_quantiles_equal_the_torch_ones(rng):
    edges = np.linspace(0.0, 4.0, 101, dtype=np.float32)
    counts = rng.integers(0, 5, size=(64, 100)).astype(np.float32)
    counts[:, rng.random(100) < 0.5] = 0.0  # empty bins hold no quantile
    counts[3] = 0.0  # an empty histogram: invalid
    valid = np.ones(64, bool)
    valid[7] = False
    ours = zone_hypotheses_from_histogram(edges, counts, valid, 16)
    theirs = sample_hypotheses_from_histogram(torch.from_numpy(edges), torch.from_numpy(counts),
                                              torch.from_numpy(valid), 16).numpy()
    np.testing.assert_allclose(ours, theirs, atol=1e-6, rtol=0)
    assert np.all(ours[[3, 7]] == 0)


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="method"):
        zone_hypotheses(np.ones(4), np.ones(4), np.ones(4, bool), 16, "bogus")
    with pytest.raises(ValueError, match="valid"):
        zone_hypotheses(np.ones(4), np.ones(4), np.ones(4), 16)
    with pytest.raises(ValueError, match="sigma_m"):
        zone_hypotheses(np.ones(4), -np.ones(4), np.ones(4, bool), 16)
    with pytest.raises(ValueError, match="num_samples"):
        zone_hypotheses(np.ones(4), np.ones(4), np.ones(4, bool), 1)
    with pytest.raises(ValueError, match="edges_m"):
        zone_hypotheses_from_histogram(np.array([0.0, 0.0, 1.0]), np.ones((4, 2)),
                                       np.ones(4, bool))
    with pytest.raises(ValueError, match="counts"):
        zone_hypotheses_from_histogram(np.linspace(0, 1, 3), -np.ones((4, 2)), np.ones(4, bool))
