"""Tests of depth-hypothesis sampling (deltar.sensor.sampling)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from deltar.sensor import sample_hypotheses, sample_hypotheses_from_histogram
from deltar.sensor.sampling import icdf_probabilities

PROBS = np.linspace(1e-3, 1 - 1e-3, 16)


def test_reproduces_the_official_icdf_samples(parity_fixture_path):
    fixture = torch.load(parity_fixture_path, weights_only=False)
    assert len(fixture["cases"]) == 3
    for case in fixture["cases"]:
        mean_sigma = case["zone_mean_sigma_m"]
        samples = sample_hypotheses(mean_sigma[:, 0], mean_sigma[:, 1], case["zone_valid"],
                                    num_samples=16, method="icdf")
        expected = case["zone_samples_icdf16"]
        assert samples.shape == expected.shape == (64, 16)
        assert samples.dtype == torch.float32
        torch.testing.assert_close(samples, expected, atol=1e-5, rtol=0, msg=case["name"])


def test_icdf_matches_scipy_normal_quantiles(rng):
    mean = rng.uniform(0.2, 4.0, size=(3, 64))
    sigma = rng.uniform(0.001, 0.8, size=(3, 64))
    valid = np.ones((3, 64), dtype=bool)
    samples = sample_hypotheses(torch.from_numpy(mean), torch.from_numpy(sigma),
                                torch.from_numpy(valid), num_samples=16)
    assert samples.shape == (3, 64, 16) and samples.dtype == torch.float64
    expected = stats.norm.ppf(PROBS, loc=mean[..., None], scale=sigma[..., None])
    np.testing.assert_allclose(samples.numpy(), np.maximum(expected, 0.0), atol=1e-9)


def test_uniform_spans_three_sigma(rng):
    mean = rng.uniform(0.2, 4.0, size=36).astype(np.float32)
    sigma = rng.uniform(0.0, 0.5, size=36).astype(np.float32)
    samples = sample_hypotheses(torch.from_numpy(mean), torch.from_numpy(sigma),
                                torch.ones(36, dtype=torch.bool), num_samples=16,
                                method="uniform")
    expected = np.linspace(mean - 3 * sigma, mean + 3 * sigma, 16, axis=-1)
    np.testing.assert_allclose(samples.numpy(), np.maximum(expected, 0.0), atol=1e-6)


@pytest.mark.parametrize("method", ["icdf", "uniform"])
def test_zero_sigma_gives_the_mean(method):
    mean = torch.tensor([1.5, 2.25, 0.7])
    samples = sample_hypotheses(mean, torch.zeros(3), torch.ones(3, dtype=torch.bool),
                                num_samples=8, method=method)
    assert torch.equal(samples, mean[:, None].expand(3, 8))


@pytest.mark.parametrize("method", ["icdf", "uniform"])
def test_invalid_zones_are_zero_even_with_garbage(method):
    mean = torch.tensor([[1.0, float("nan"), 2.0]])
    sigma = torch.tensor([[0.1, -1.0, 0.2]])
    valid = torch.tensor([[True, False, True]])
    samples = sample_hypotheses(mean, sigma, valid, num_samples=4, method=method)
    assert samples.shape == (1, 3, 4)
    assert torch.equal(samples[0, 1], torch.zeros(4))
    assert (samples[0, [0, 2]] > 0).all()
    assert (samples.diff(dim=-1)[0, [0, 2]] > 0).all()  # increasing along K


def test_bad_inputs_raise():
    ones = torch.ones(4)
    valid = torch.ones(4, dtype=torch.bool)
    with pytest.raises(ValueError, match="method"):
        sample_hypotheses(ones, ones, valid, method="random")
    with pytest.raises(ValueError, match="sigma_m"):
        sample_hypotheses(ones, -ones, valid)
    with pytest.raises(ValueError, match="finite"):
        sample_hypotheses(torch.tensor([1.0, float("nan"), 1, 1]), ones, valid)
    with pytest.raises(ValueError, match="sigma_m"):
        sample_hypotheses(ones, torch.ones(5), valid)
    with pytest.raises(ValueError, match="valid"):
        sample_hypotheses(ones, ones, torch.ones(4))
    with pytest.raises(ValueError, match="num_samples"):
        sample_hypotheses(ones, ones, valid, num_samples=1)


def test_probabilities():
    probs = icdf_probabilities(16, torch.float64)
    np.testing.assert_allclose(probs.numpy(), PROBS, atol=1e-15)


def test_histogram_icdf_matches_piecewise_linear_cdf_inverse(rng):
    edges = np.arange(11) * 0.1
    counts = rng.uniform(1.0, 10.0, size=(2, 5, 10))  # no empty bins: CDF strictly increasing
    samples = sample_hypotheses_from_histogram(torch.from_numpy(edges), torch.from_numpy(counts),
                                               torch.ones(2, 5, dtype=torch.bool))
    assert samples.shape == (2, 5, 16) and samples.dtype == torch.float64
    for b in range(2):
        for z in range(5):
            cdf = np.concatenate([[0.0], np.cumsum(counts[b, z]) / counts[b, z].sum()])
            np.testing.assert_allclose(samples[b, z].numpy(), np.interp(PROBS, cdf, edges),
                                       atol=1e-12)


def test_histogram_samples_avoid_empty_bins_and_handle_invalid():
    edges = torch.arange(101, dtype=torch.float32) * 0.04
    counts = torch.zeros(3, 100)
    counts[0, 25] = 50.0  # one bin: all samples inside [1.00, 1.04]
    counts[1, 10:12] = 30.0  # two separate clusters
    counts[1, 60:63] = 10.0
    valid = torch.tensor([True, True, True])  # zone 2 has no counts: treated as invalid
    samples = sample_hypotheses_from_histogram(edges, counts, valid, num_samples=16)
    assert samples.dtype == torch.float32
    assert ((samples[0] >= 1.0) & (samples[0] <= 1.04)).all()
    in_first = (samples[1] >= 0.40) & (samples[1] <= 0.48)
    in_second = (samples[1] >= 2.40) & (samples[1] <= 2.52)
    assert (in_first | in_second).all()
    # 60 of 90 counts: the first cluster takes the probabilities below 2/3, that is
    # 0.001 + k * 0.998 / 15 < 2/3 for k = 0..10.
    assert int(in_first.sum()) == 11
    assert torch.equal(samples[2], torch.zeros(16))
    invalid = sample_hypotheses_from_histogram(edges, counts, torch.tensor([False, True, True]))
    assert torch.equal(invalid[0], torch.zeros(16))


def test_histogram_of_gaussian_approximates_gaussian_quantiles():
    gen = torch.Generator().manual_seed(0)
    depth = 2.0 + 0.3 * torch.randn(200000, generator=gen, dtype=torch.float64)
    edges = torch.arange(101, dtype=torch.float64) * 0.04
    counts = torch.histc(depth, bins=100, min=0, max=4.0)
    samples = sample_hypotheses_from_histogram(edges, counts[None], torch.tensor([True]))
    expected = stats.norm.ppf(PROBS, loc=2.0, scale=0.3)
    np.testing.assert_allclose(samples[0].numpy(), expected, atol=0.04)


def test_histogram_bad_inputs_raise():
    edges = torch.arange(5, dtype=torch.float32)
    with pytest.raises(ValueError, match="edges_m"):
        sample_hypotheses_from_histogram(torch.tensor([0.0, 2.0, 1.0]), torch.ones(1, 2),
                                         torch.ones(1, dtype=torch.bool))
    with pytest.raises(ValueError, match="counts"):
        sample_hypotheses_from_histogram(edges, torch.ones(2, 3), torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="counts"):
        sample_hypotheses_from_histogram(edges, -torch.ones(2, 4), torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="valid"):
        sample_hypotheses_from_histogram(edges, torch.ones(2, 4), torch.ones(3, dtype=torch.bool))


@pytest.mark.parametrize("method", ["icdf", "uniform"])
def test_wide_zones_near_the_sensor_get_no_negative_distance(method):
    # A real frame had a zone at 0.27 m with sigma 0.63 m: its lowest quantiles are < 0.
    mean, sigma = torch.tensor([0.27, 2.0]), torch.tensor([0.63, 0.05])
    samples = sample_hypotheses(mean, sigma, torch.tensor([True, True]), 16, method)
    assert (samples >= 0).all() and samples[0, 0] == 0.0 and samples[0, -1] > 1.0
    assert torch.all(samples[:, 1:] >= samples[:, :-1])
    torch.testing.assert_close(samples[1].mean(), torch.tensor(2.0), atol=1e-6, rtol=0)
