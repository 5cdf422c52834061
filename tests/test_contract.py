"""The input contract's constants agree with the network and the sampler that use them."""

from __future__ import annotations

import pytest
import torch

from deltar.contract import HYPOTHESIS_SAMPLINGS, SIZE_DIVISOR


def test_the_size_divisor_is_the_encoders_coarsest_stride():
    from deltar.models.encoders import FEATURE_STRIDES

    assert max(FEATURE_STRIDES) == SIZE_DIVISOR


@pytest.mark.parametrize("method", HYPOTHESIS_SAMPLINGS)
def test_every_sampling_name_samples(method):
    from deltar.sensor.sampling import sample_hypotheses

    mean, sigma = torch.tensor([1.0, 2.0]), torch.tensor([0.1, 0.2])
    out = sample_hypotheses(mean, sigma, torch.tensor([True, False]), 8, method)
    assert out.shape == (2, 8) and torch.all(out[1] == 0) and torch.all(out[0] > 0)


def test_an_unknown_sampling_name_is_refused():
    from deltar.sensor.sampling import sample_hypotheses

    with pytest.raises(ValueError, match="icdf"):
        sample_hypotheses(torch.ones(1), torch.ones(1), torch.ones(1, dtype=torch.bool), 4,
                          "normal")
